"""Shared file formats: one home for each file format more than one part of PreSim writes or reads.

Modules (each one rule, documented in docs/scene-format.md, "Shared file formats"):

- :mod:`presim.formats.png`: PNG bytes of an RGB / gray / uint16 / boolean image.
- :mod:`presim.formats.depth_png`: metres -> 16-bit depth PNG with a depth scale, one overflow rule
  and a count of the pixels it could not store.
- :mod:`presim.formats.tum`: TUM trajectories (``stamp x y z qx qy qz qw``), the one strict reader
  (every TUM trajectory PreSim reads goes through it), pose interpolation and the writer.
- :mod:`presim.formats.kinfu_folder`: the KinectFusion / 7-Scenes capture folder writer (what
  ``presim drive --record`` and ``presim render`` write and the ``kinfu`` importer reads).
- :mod:`presim.formats.ply`: the PLY reader / writer of point clouds and object models.
- :mod:`presim.formats.bop`: the BOP record types and JSON files (one record per BOP row).

Readers and writers here only translate between bytes on disk and arrays / records in memory.
Layering: this package sits just above :mod:`presim.geometry` and :mod:`presim.io_utils` and imports
nothing else of PreSim, so every layer above (capture, synthesis, sim, datasets, outputs, cli) may
use it. Nothing heavy is imported here.
"""
