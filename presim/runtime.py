"""Process-wide settings that the renderer's speed depends on: :func:`configure`.

``import presim`` leaves the process alone; :func:`configure` applies these settings, once
(idempotent). The ``presim`` command line calls it first thing, the Gymnasium environments when they
are constructed, the benchmarks after their imports. A library user calls it first thing too,
before importing torch or running any renderer kernel::

    import presim.runtime
    presim.runtime.configure()
    from presim.synthesis.renderer import Renderer   # ...

What it does (a value the user set always wins):

1. ``OMP_WAIT_POLICY=PASSIVE`` unless set. The numba kernels run on OpenMP threads; GNU OpenMP's
   default lets idle threads spin for a while after each parallel region, and the renderer launches
   many short regions between OpenCV/numpy calls, so spinning threads stole the cores from them: 2
   threads were no faster than 1 on an idle 2-core machine and 2.6x slower with one other busy
   process (benchmarks/bench_render.py, docs/synthesis.md). libgomp reads the policy once, when it
   loads (``import torch``, or numba's first parallel kernel), hence "first thing".
2. When libgomp is already loaded (``import torch`` came first) it is too late for the policy: it
   spins, and numba's OpenMP layer binds to that runtime (measured: 1.7x the CPU per 640x480
   frame, docs/synthesis.md "Threads"). numba's own work queue sleeps like PASSIVE OpenMP (same CPU
   per frame measured), so ``NUMBA_THREADING_LAYER=workqueue`` then, unless the user chose a layer.
   Safe here: the simulator launches parallel kernels from one thread at a time.
3. :func:`keep_freed_memory` (below).
4. Hides numba's warning that the system's TBB is too old (it then uses OpenMP: not the user's
   problem).

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
import warnings

__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "configure", "keep_freed_memory"]

MMAP_THRESHOLD_BYTES = 32 << 20
"""Allocations below this come from the heap (glibc's ``M_MMAP_THRESHOLD``; 32 MiB is its maximum)."""
TRIM_THRESHOLD_BYTES = 256 << 20
"""Free memory at the top of a heap kept before it is returned to the kernel (``M_TRIM_THRESHOLD``)."""

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_USER_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")
_applied: bool | None = None
_configured = False
TBB_WARNING = "The TBB threading layer requires TBB version"
"""Start of numba's warning about an old system TBB (filtered by :func:`configure`)."""


def _gomp_loaded() -> bool:
    """True when a GNU OpenMP runtime is already loaded in this process (e.g. by ``import torch``)."""
    try:
        with open("/proc/self/maps") as f:
            return "libgomp" in f.read()
    except OSError:  # not Linux: look for the usual importer
        return "torch" in sys.modules


def configure() -> None:
    """Apply the process settings of the module docstring (thread wait policy, numba threading layer
    when torch's OpenMP is already loaded, malloc thresholds, one warning filter). Idempotent: only
    the first call does anything. Environment variables the user set are never changed.
    """
    global _configured
    if _configured:
        return
    _configured = True
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        if "NUMBA_THREADING_LAYER" not in os.environ and _gomp_loaded():
            os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
            if "numba" in sys.modules:  # read at numba's import; takes effect before its first parallel launch
                sys.modules["numba"].config.THREADING_LAYER = "workqueue"
    keep_freed_memory()
    warnings.filterwarnings("ignore", message=TBB_WARNING)


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
