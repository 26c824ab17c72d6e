"""How many numba threads one frame uses (issue 13: small frames run on one thread).

numba's parallel kernels run on an OpenMP team whose idle threads sleep (``OMP_WAIT_POLICY=PASSIVE``,
set by ``presim/__init__.py``: spinning threads cost 1.7x the CPU and 2.6x the time beside a busy
process). Waking a sleeping thread costs each parallel region ~0.1-0.4 ms of wall time on the
2-core machine; a frame runs 4-6 parallel regions per warped view. At 128x128 a region's work is a
few tens of microseconds, so the wake-ups cost more than the second thread gives: the apc capture
renders 1.45x and the sample scene 1.13x faster (wall) on one thread there; from 256x256 on two
threads are as fast or faster (docs/synthesis.md, "Threads per frame"). The output does not depend
on the thread count (every kernel's result is thread-count independent, tested).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numba

__all__ = ["SERIAL_MAX_PIXELS", "frame_threads", "numba_threads"]

SERIAL_MAX_PIXELS = 40_000
"""Frames of at most this many pixels render on one numba thread when ``RenderConfig.threads`` is
0 (auto): 128x96, 128x128, 160x120, 200x200. Measured on the 2-core machine, wall ms per frame, one
against two threads: 128x128 1.13-1.61x and 160x120 1.35x in favour of one thread; 256x256
(65 536 px) was a draw (apc capture 1.08x for one thread, the sample scene 0.80x in an A/B run);
320x240 and up 0.77-0.82x (two threads win)."""


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


@contextmanager
def numba_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` numba threads in this thread, then restore the previous count."""
    prev = numba.get_num_threads()
    if n == prev:
        yield
        return
    numba.set_num_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(prev)
