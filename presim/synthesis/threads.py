"""How many numba threads one frame uses (issue 13: small frames run on one thread).

numba's parallel kernels run on an OpenMP team whose idle threads sleep (``OMP_WAIT_POLICY=PASSIVE``,
set by ``presim/__init__.py``: spinning threads cost 1.7x the CPU and 2.6x the time beside a busy
process). Waking a sleeping thread costs each parallel region ~0.1-0.4 ms of wall time on the
2-core machine; a frame runs 4-6 parallel regions per warped view. At 128x128 a region's work is a
few tens of microseconds, so the wake-ups cost more than the second thread gives: the apc capture
renders 1.45x and the sample scene 1.13x faster (wall) on one thread there; from 256x256 on two
threads are as fast or faster (docs/synthesis.md, "Threads per frame"). The output does not depend
on the thread count (every kernel's result is thread-count independent, tested).

**Serial twins.** Every parallel kernel of the synthesis is declared with :func:`parallel_kernel`,
which compiles its Python function twice: with ``parallel=True`` (``prange`` spread over numba's
threads) and serially (``prange`` = ``range``) with ``nogil=True``. A Python thread inside
:func:`numba_threads` ``(1)`` (every frame of at most :data:`SERIAL_MAX_PIXELS` pixels) or
:func:`serial_kernels` runs the serial twins: the same arithmetic in the same order, so the same
output, without a parallel launch and without holding the GIL. That is what lets several Python
threads render small frames at once (:meth:`presim.synthesis.renderer.Renderer.render_batch` with
``RenderConfig.batch_threads``, the vector environment), and the view cache's background thread
build views beside a rendering thread, under any numba threading layer (``workqueue`` forbids
parallel kernels launched from two threads at once).
"""

from __future__ import annotations

import functools
import threading
import types
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numba

__all__ = ["SERIAL_MAX_PIXELS", "LIGHT_SERIAL_BELOW", "frame_threads", "numba_threads", "serial_kernels", "serial_now",
           "parallel_kernel", "TwinKernel"]

SERIAL_MAX_PIXELS = 40_000
"""Frames of at most this many pixels render on one numba thread when ``RenderConfig.threads`` is
0 (auto): 128x96, 128x128, 160x120, 200x200. Measured on the 2-core machine, wall ms per frame, one
against two threads: 128x128 1.13-1.61x and 160x120 1.35x in favour of one thread; 256x256
(65 536 px) was a draw (apc capture 1.08x for one thread, the sample scene 0.80x in an A/B run);
320x240 and up 0.77-0.82x (two threads win)."""


LIGHT_SERIAL_BELOW = {"map": 1 << 20, "pass": 150_000}
"""``serial_below`` of the light per-view kernels (pixels), measured on the 2-core machine with
two threads, wall µs per call, parallel against serial twin (docs/synthesis.md, "Light kernels on
one thread"): ``"map"``, a pass that reads one mask and touches little else (a later view's merge
on its replaceable pixels, apc capture: 256x256 90 → 46, 640x480 134 → 106); ``"pass"``, a pass
that reads and writes several images (the first view's merge + hole mask, the fill's full-size
pull and push: merge 256x256 112 → 64, 320x240 133 → 88, but 640x480 313 → 333 and 640x360
228 → 296)."""


def frame_threads(width: int, height: int, threads: int = 0) -> int:
    """Numba threads for rendering one ``width`` x ``height`` frame.

    Args:
        threads: > 0: that many (at most numba's pool size); 0 = auto: one thread up to
            :data:`SERIAL_MAX_PIXELS` pixels, else the calling thread's current count
            (``numba.get_num_threads()``, which a caller may have lowered).
    """
    if threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    if threads > 0:
        return min(threads, numba.config.NUMBA_NUM_THREADS)
    return 1 if width * height <= SERIAL_MAX_PIXELS else numba.get_num_threads()


_local = threading.local()  # .serial: this Python thread runs the serial twins


def serial_now() -> bool:
    """True when this Python thread runs the serial twins of the parallel kernels."""
    return getattr(_local, "serial", False)


@contextmanager
def serial_kernels(on: bool = True) -> Iterator[None]:
    """Run the block's parallel kernels as their serial, GIL-free twins in this Python thread
    (``on`` False: as they are), then restore the previous mode."""
    prev = serial_now()
    _local.serial = bool(on)
    try:
        yield
    finally:
        _local.serial = prev


@contextmanager
def numba_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` numba threads in this thread, then restore the previous count.
    With ``n`` = 1 the block's parallel kernels run as their serial twins (:func:`serial_kernels`:
    same output, no parallel launch, the GIL released)."""
    prev = numba.get_num_threads()
    with serial_kernels(n == 1 or serial_now()):
        if n == prev:
            yield
            return
        numba.set_num_threads(n)
        try:
            yield
        finally:
            numba.set_num_threads(prev)


class TwinKernel:
    """A numba kernel compiled twice from one Python function (see the module doc): ``parallel``
    (``parallel=True``) and ``serial`` (``prange`` runs as ``range``, ``nogil=True``). Calling it runs
    the serial twin in a thread inside :func:`serial_kernels`, else the parallel one. Both are
    compiled lazily, on first call, and cached on disk separately.

    ``serial_below`` (> 0): a light kernel whose work is one cheap pass over an image also runs its
    serial twin when the array argument number ``size_arg`` has fewer than ``serial_below``
    elements: waking the second thread costs more than half of such a pass there (same output;
    :data:`LIGHT_SERIAL_BELOW`)."""

    def __init__(self, fn: Callable, serial_below: int = 0, size_arg: int = 0, **options: Any):
        self.py_func = fn
        self.serial_below = int(serial_below)
        self.size_arg = int(size_arg)
        self.parallel = numba.njit(parallel=True, **options)(fn)
        # A copy under its own name, so that numba's on-disk cache keeps the two compilations apart.
        twin = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + "_serial", fn.__defaults__,
                                  fn.__closure__)
        twin.__qualname__ = fn.__qualname__ + "_serial"
        twin.__module__ = fn.__module__
        self.serial = numba.njit(nogil=True, **options)(twin)
        functools.update_wrapper(self, fn)

    def __call__(self, *args: Any) -> Any:
        if getattr(_local, "serial", False) or (self.serial_below and args[self.size_arg].size < self.serial_below):
            return self.serial(*args)
        return self.parallel(*args)


def parallel_kernel(serial_below: int = 0, size_arg: int = 0, **options: Any) -> Callable[[Callable], TwinKernel]:
    """Decorator: ``@parallel_kernel(cache=True, fastmath=...)`` instead of
    ``@numba.njit(parallel=True, ...)`` makes a :class:`TwinKernel` (``serial_below`` / ``size_arg``:
    see there). The synthesis kernels also pass ``error_model="numpy"`` (no ZeroDivisionError
    branch, which keeps loops with a division from vectorizing; tested for every kernel)."""
    return lambda fn: TwinKernel(fn, serial_below, size_arg, **options)
