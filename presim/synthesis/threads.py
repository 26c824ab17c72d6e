"""How many numba threads one frame uses, and the serial GIL-free twins of the parallel kernels.

Idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE``, set by ``presim/__init__.py``); waking one costs each
parallel region ~0.1-0.4 ms on the 2-core machine, more than a small frame's region gains, so frames of at most
:data:`SERIAL_MAX_PIXELS` pixels run on one thread (docs/synthesis.md, "Threads per frame"). Every parallel kernel
is declared with :func:`parallel_kernel`, compiled twice: ``parallel=True`` and serially with ``nogil=True``. A
thread inside :func:`numba_threads` ``(1)`` or :func:`serial_kernels` runs the serial twins (same arithmetic and
order, same output), so several Python threads (warp-ahead, the view cache's background builds) can run kernels at
once under any threading layer. Outputs never depend on the thread count (tested).
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
"""Frames of at most this many pixels render on one numba thread with ``PerfConfig.threads`` = 0 (auto): one
thread is 1.13-1.61x faster at 128x128 on the 2-core machine, 256x256 is a draw, two win from 320x240."""


LIGHT_SERIAL_BELOW = {"map": 1 << 20, "pass": 150_000}
"""``serial_below`` (pixels) of the light per-view kernels (docs/synthesis.md, "Light kernels on one thread"):
``"map"`` for passes reading one mask (a later view's merge: 256x256 90 -> 46 us serial), ``"pass"`` for passes
over several images (first merge + hole mask, fill pull/push: serial faster up to 320x240, slower at 640x480)."""


def frame_threads(width: int, height: int, threads: int = 0) -> int:
    """Numba threads for rendering one ``width`` x ``height`` frame.

    threads: > 0: that many (at most numba's pool size); 0 = auto: one up to :data:`SERIAL_MAX_PIXELS` pixels,
    else the calling thread's ``numba.get_num_threads()``.
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
    """Run the block's parallel kernels as their serial, GIL-free twins in this thread (``on`` False: as they are)."""
    prev = serial_now()
    _local.serial = bool(on)
    try:
        yield
    finally:
        _local.serial = prev


@contextmanager
def numba_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` numba threads in this thread (``n`` = 1: the serial twins), then restore the count."""
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
    """A numba kernel compiled twice from one function: ``parallel`` and ``serial`` (``prange`` = ``range``,
    ``nogil=True``), both lazily and cached on disk separately. Calls run the serial twin inside
    :func:`serial_kernels` or when argument ``size_arg`` has fewer than ``serial_below`` (> 0) elements
    (:data:`LIGHT_SERIAL_BELOW`), else the parallel one."""

    def __init__(self, fn: Callable, serial_below: int = 0, size_arg: int = 0, **options: Any):
        self.py_func = fn
        self.serial_below = int(serial_below)
        self.size_arg = int(size_arg)
        self.parallel = numba.njit(parallel=True, **options)(fn)
        # A copy under its own name keeps the two compilations apart in numba's on-disk cache.
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
    """Decorator replacing ``@numba.njit(parallel=True, ...)``: makes a :class:`TwinKernel`. Synthesis kernels
    pass ``error_model="numpy"`` (no ZeroDivisionError branch, which keeps division loops from vectorizing)."""
    return lambda fn: TwinKernel(fn, serial_below, size_arg, **options)
