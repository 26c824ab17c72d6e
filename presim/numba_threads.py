"""Numba threads per frame, and the serial GIL-free twin of every parallel kernel of presim.

Waking an idle OpenMP thread costs each parallel region ~0.1-0.4 ms on 2 cores, more than a small frame gains,
so frames of at most :data:`SERIAL_MAX_PIXELS` pixels run on one thread. :func:`parallel_kernel` compiles a kernel
twice (``parallel=True``, and serial with ``nogil=True``); inside :func:`numba_threads` ``(1)`` or
:func:`serial_kernels` a Python thread runs the serial twins, so helper threads can run kernels at once under any
threading layer. Outputs never depend on the thread count (tested). Kernels that share state with another thread
read and write it with :func:`load_acquire` / :func:`store_release` (atomic int32, acquire / release order)."""

from __future__ import annotations

import functools
import threading
import types
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numba
from numba import types as nbtypes
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["SERIAL_MAX_PIXELS", "LIGHT_SERIAL_BELOW", "frame_threads", "numba_threads", "serial_kernels", "serial_now",
           "parallel_kernel", "TwinKernel", "store_release", "load_acquire"]

SERIAL_MAX_PIXELS = 40_000
"""Frames of at most this many pixels render on one numba thread with the renderer's ``PerfConfig.threads`` = 0
(:mod:`presim.synthesis.config`): 1.13-1.61x faster at 128x128 on 2 cores, 256x256 a draw, two threads win from
320x240."""

LIGHT_SERIAL_BELOW = {"map": 1 << 20, "pass": 150_000}
"""``serial_below`` (pixels) of the light per-view kernels: ``"map"`` for passes reading one mask (a later view's
merge: 256x256 90 -> 46 us serial), ``"pass"`` for passes over several images (serial faster up to 320x240)."""


def frame_threads(width: int, height: int, threads: int = 0) -> int:
    """Numba threads for one ``width`` x ``height`` frame: ``threads`` > 0 that many (at most the pool size);
    0 = one up to :data:`SERIAL_MAX_PIXELS` pixels, else ``numba.get_num_threads()``."""
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
    """A kernel compiled ``parallel`` and ``serial`` (``prange`` = ``range``, ``nogil``), each cached on disk.
    Calls run the serial twin inside :func:`serial_kernels` or when argument ``size_arg`` has fewer than
    ``serial_below`` (> 0) elements, else the parallel one."""

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
    """Decorator replacing ``@numba.njit(parallel=True, ...)``: a :class:`TwinKernel`. The project's kernels pass
    ``error_model="numpy"`` (no ZeroDivisionError branch, which keeps division loops from vectorizing)."""
    return lambda fn: TwinKernel(fn, serial_below, size_arg, **options)


@intrinsic
def store_release(typingctx, arr, idx, val):  # pragma: no cover - compiled into the kernel
    """``arr[idx] = val`` (int32 array) as an atomic store with release order."""
    if not isinstance(arr, nbtypes.Array) or arr.dtype != nbtypes.int32:
        return None

    def codegen(context, builder, signature, args):
        aryty, idxty, valty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary,
                                       [context.cast(builder, args[1], idxty, nbtypes.intp)])
        builder.store_atomic(context.cast(builder, args[2], valty, aryty.dtype), ptr, ordering="release", align=4)
        return context.get_dummy_value()

    return nbtypes.void(arr, idx, val), codegen


@intrinsic
def load_acquire(typingctx, arr, idx):  # pragma: no cover - compiled into the kernel
    """``arr[idx]`` (int32 array) as an atomic load with acquire order (read anew each time)."""
    if not isinstance(arr, nbtypes.Array) or arr.dtype != nbtypes.int32:
        return None

    def codegen(context, builder, signature, args):
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary,
                                       [context.cast(builder, args[1], idxty, nbtypes.intp)])
        return builder.load_atomic(ptr, ordering="acquire", align=4)

    return nbtypes.int32(arr, idx), codegen
