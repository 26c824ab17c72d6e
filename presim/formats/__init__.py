"""File formats shared by several sub-packages (PLY, BOP records, depth PNGs, ...): readers and writers
that only translate between bytes on disk and arrays/records in memory."""
