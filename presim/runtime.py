"""Process-wide settings that the renderer's speed depends on (applied by ``import presim``).

:func:`keep_freed_memory` — glibc's allocator returns freed memory to the kernel eagerly: large
arrays are mapped fresh for every allocation (above a threshold that moves with use) and the top of
each heap is trimmed. A frame allocates ~8 MB of short-lived arrays at 640x480 (accumulators, hole
masks, crack-pass outputs, fill buffers), on the main thread and in the numba worker threads'
arenas, so every frame paid ~2 000-4 700 minor page faults: the kernel zeroing fresh pages. With
allocations up to 32 MB served from the heap and 256 MB of free heap kept before trimming, a
steady-state frame takes 0 faults (640x480, children alternating the setting on and off: apc capture
with refined depth 1.08-1.09x and the sample scene 1.14x less CPU per frame; docs/synthesis.md,
"Threads per frame, freed memory").
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "keep_freed_memory"]

MMAP_THRESHOLD_BYTES = 32 << 20
"""Allocations below this come from the heap (glibc's ``M_MMAP_THRESHOLD``; 32 MiB is its maximum)."""
TRIM_THRESHOLD_BYTES = 256 << 20
"""Free memory at the top of a heap kept before it is returned to the kernel (``M_TRIM_THRESHOLD``)."""

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_USER_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")
_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to keep freed memory for reuse (module docstring). Idempotent.

    Skipped (returns False) when ``PRESIM_KEEP_FREED_MEMORY=0``, when the user tuned malloc through
    its own environment variables (``MALLOC_*_`` or ``GLIBC_TUNABLES``: their choice wins), and off
    glibc (macOS, Windows, musl). Returns True when both settings were applied.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get("PRESIM_KEEP_FREED_MEMORY", "1") == "0" or any(v in os.environ for v in _USER_VARS):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _applied = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    return _applied
