"""Single-threaded twins of numba's parallel kernels, for images too small to share out.

A parallel region has a fixed cost per call (threads woken, work handed out, joined; the idle
worker keeps spinning for a while afterwards and that counts as CPU time); on a 128 x 128 frame
the kernels' own work is a few tens of microseconds, the same order. :func:`serial_twin` compiles
the very same Python function a second time without ``parallel`` (``prange`` then runs as
``range``: same arithmetic, same order within each iteration, so the same output), cached on disk
under its own name. Callers pick the twin below :data:`SERIAL_MAX_PIXELS` (:func:`pick`).
"""

from __future__ import annotations

import types
from typing import Any

import numba as nb

__all__ = ["SERIAL_MAX_PIXELS", "serial_twin", "pick"]

SERIAL_MAX_PIXELS = 70_000
"""Images of fewer pixels (128 x 128, 128 x 96, 256 x 256) run the single-threaded twins of the
light per-pixel kernels (merge + hole mask, big-hole mask: ~1 ns of work per pixel). Measured in
docs/synthesis.md ("Small frames"). The heavier kernels (warp, crack pass) stay parallel at every
size: their twins measured no better, or slower (numba's parallel lowering also compiles the
loop body better)."""


def serial_twin(kernel: Any, **options: Any) -> Any:
    """The numba kernel ``kernel`` (a ``parallel=True`` dispatcher) compiled again single-threaded
    (``options``: other ``njit`` flags to keep, e.g. ``fastmath``), cached under ``<name>_serial``."""
    f = kernel.py_func
    g = types.FunctionType(f.__code__, f.__globals__, f.__name__ + "_serial", f.__defaults__, f.__closure__)
    g.__qualname__ = f.__qualname__ + "_serial"
    g.__module__ = f.__module__
    g.__doc__ = f.__doc__
    return nb.njit(cache=True, **options)(g)


def pick(parallel: Any, serial: Any, pixels: int) -> Any:
    """``serial`` below :data:`SERIAL_MAX_PIXELS` pixels, else ``parallel``."""
    return serial if pixels < SERIAL_MAX_PIXELS else parallel
