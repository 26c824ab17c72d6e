"""Later candidate views warped on a helper thread while the main thread runs the adaptive loop.

:class:`WarpAhead` warps and crack-filters the views in one GIL-free numba call per frame (:func:`_warp_jobs_kernel`:
culling, serial warp, banded crack pass). Jobs have int32 states shared by both threads (queued, running, done, claimed;
``done`` stored with release order after the images): :meth:`WarpAhead.take` uses a done job, waits for a running one,
or claims a queued one for the loop. The images equal the loop's own (same kernels and inputs, tested)."""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass
from typing import Any, NamedTuple

import numba as nb
import numpy as np

from presim.geometry import Intrinsics
from presim.numba_threads import load_acquire, store_release
from presim.synthesis.cracks import BAND_ROWS, LOWEST_SET_BIT, banded_crack_kernel
from presim.synthesis.warp import (CULL_MARGIN, chunk_bounds_of, chunk_keep_kernel, target_cam, tile_marks,
                                   warp_layers_kernel)

__all__ = ["WarpAhead", "MAX_JOBS", "WARP_AHEAD_MIN_POINTS"]

MAX_JOBS = 8
"""At most this many views per frame (the kernel takes fixed-size tuples: one compilation)."""

WARP_AHEAD_MIN_POINTS = 10_000
"""Views of fewer points are warped by the loop: the handover (~34-107 us per frame) costs about as much as
warping them (~5-9 ns per point)."""

QUEUED, RUNNING, DONE, CLAIMED = 0, 1, 2, 3  # job states (int32)

_warp_serial = warp_layers_kernel.serial
_crack_serial = banded_crack_kernel.serial
_NO_MASK = np.zeros((1, 1), np.bool_)


class Jobs(NamedTuple):
    """One frame's jobs: per view (tuples of :data:`MAX_JOBS`) points, chunk bounds and output buffers."""

    xyz: tuple
    rgb: tuple
    layer_start: tuple
    bounds: tuple  # :class:`~presim.synthesis.warp.ChunkBounds` per view
    zb: tuple
    cb: tuple
    d: tuple
    c: tuple


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _warp_jobs_kernel(state, cancel, n, jobs, cam, cam64, tm, band):  # pragma: no cover
    # Jobs k < n in order: warp_layers(view k) without tiles into zb[k] / cb[k], then filtered_composite_banded
    # (no replace mask) into d[k] / c[k]. Claimed jobs are skipped; cancel[0] set (the loop has ended) stops it.
    for k in range(n):
        if load_acquire(cancel, 0) != 0:
            return
        if load_acquire(state, k) != QUEUED:
            continue
        store_release(state, k, RUNNING)
        b = jobs.bounds[k]
        vis = np.ones(b.lo.shape[1], np.uint8)
        if cam.near > 0 and b.abs_max < np.inf:
            chunk_keep_kernel(b, cam64, CULL_MARGIN, tm, vis)
        # the crack pass reads colour only where depth > 0: no clearing needed
        _warp_serial(jobs.xyz[k], jobs.rgb[k], jobs.layer_start[k], 1, cam, tm, vis, False, jobs.zb[k], jobs.cb[k])
        if load_acquire(cancel, 0) != 0:  # nobody will read it: no crack pass, not done
            store_release(state, k, CLAIMED)
            return
        _crack_serial(jobs.zb[k], jobs.cb[k], LOWEST_SET_BIT, _NO_MASK, False, _NO_MASK, band, jobs.d[k], jobs.c[k])
        store_release(state, k, DONE)  # after the images: the loop reads them once it sees DONE


class _Buffers:
    """One set of per-job output buffers (layers and images), reused by every other frame."""

    def __init__(self) -> None:
        self.zb: list[np.ndarray] = []
        self.cb: list[np.ndarray] = []
        self.d: list[np.ndarray] = []
        self.c: list[np.ndarray] = []
        self.user: _Frame | None = None  # the last frame that used the set

    def fit(self, views: list[Any], H: int, W: int) -> None:
        """Buffers for ``views`` at H x W (kept when they fit)."""
        for k, v in enumerate(views):
            shape = (v.num_layers, H, W)
            if k == len(self.zb):
                self.zb.append(np.empty(shape, np.float32))
                self.cb.append(np.empty(shape + (3,), np.uint8))
                self.d.append(np.empty((H, W), np.float32))
                self.c.append(np.empty((H, W, 3), np.uint8))
            if self.zb[k].shape != shape:
                self.zb[k] = np.empty(shape, np.float32)
                self.cb[k] = np.empty(shape + (3,), np.uint8)
            if self.d[k].shape != (H, W):
                self.d[k] = np.empty((H, W), np.float32)
                self.c[k] = np.empty((H, W, 3), np.uint8)

    def padded(self, name: str, n: int) -> tuple:
        """The first n buffers of ``name``, padded to :data:`MAX_JOBS` with the first (never written)."""
        got = getattr(self, name)
        return tuple(got[:n]) + (got[0],) * (MAX_JOBS - n)


@dataclass(eq=False)
class _Frame:
    """One frame's views, job states, stop flag, buffer set and kernel arguments."""

    views: list[Any]
    state: np.ndarray
    cancel: np.ndarray
    bufs: _Buffers
    args: tuple
    begun: bool = False  # the thread has taken the frame (its kernel call runs or has run)
    finished: bool = False  # the kernel call has returned (or failed)


class _Shared:
    """State shared with the thread (not the :class:`WarpAhead` itself, whose collection ends the thread)."""

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.frame: _Frame | None = None
        self.closed = False


def _fields(view: Any) -> tuple:
    """The kernel's per-view arguments (points, layer starts, chunk bounds), contiguous: one compilation."""
    c = np.ascontiguousarray
    return c(view.xyz_world), c(view.rgb), c(view.layer_start), chunk_bounds_of(view)


def _serve(sh: _Shared) -> None:
    """The thread: run each new frame's kernel call until the owner is gone."""
    while True:
        with sh.cv:
            while not sh.closed and (sh.frame is None or sh.frame.begun):
                sh.cv.wait()
            if sh.closed:
                return
            frame = sh.frame
            frame.begun = True
        try:
            _warp_jobs_kernel(*frame.args)
        except Exception:  # noqa: BLE001 - jobs left running: the loop warps those views itself
            pass
        with sh.cv:
            frame.finished = True
            sh.cv.notify_all()


def _close(sh: _Shared) -> None:
    with sh.cv:
        sh.closed = True
        sh.cv.notify_all()


class WarpAhead:
    """One helper thread that warps a frame's later candidate views ahead of the adaptive loop, for one rendering
    thread; starts on the first :meth:`start`, ends on :meth:`close` or collection."""

    def __init__(self) -> None:
        self._sh = _Shared()
        self._thread: threading.Thread | None = None
        # Two buffer sets used in turn: a new frame does not wait for the previous one's last (cancelled) warp.
        self._sets = (_Buffers(), _Buffers())
        self._turn = 0
        self.taken = 0  # views the loop took from the thread
        self._finalizer = weakref.finalize(self, _close, self._sh)

    def close(self) -> None:
        """End the thread (after a running kernel call)."""
        self._finalizer()

    def start(self, views: list[Any], T_cam_world: np.ndarray, K: Intrinsics, near_m: float) -> None:
        """Warp ``views`` (prepared :class:`~presim.synthesis.warp.ViewPoints`, likely loop order, at most
        :data:`MAX_JOBS`) and crack-filter them for this camera; unbegun older jobs are dropped."""
        views = list(views)[:MAX_JOBS]
        if not views:
            return
        sh = self._sh
        bufs = self._sets[self._turn]
        self._turn ^= 1
        with sh.cv:
            if sh.closed:
                raise RuntimeError("WarpAhead: closed")
            old = sh.frame
            if old is not None and not old.begun:
                sh.frame = None  # never begun: dropped
            while bufs.user is not None and bufs.user.begun and not bufs.user.finished:
                sh.cv.wait()  # the frame before the previous one still runs (its buffers are these)
        bufs.fit(views, K.height, K.width)
        n = len(views)
        fields = [_fields(v) for v in views]
        fields += [fields[0]] * (MAX_JOBS - n)  # fixed-size tuples; jobs >= n are never run
        state = np.full(MAX_JOBS, CLAIMED, np.int32)
        state[:n] = QUEUED
        cancel = np.zeros(1, np.int32)
        jobs = Jobs(*zip(*fields), bufs.padded("zb", n), bufs.padded("cb", n), bufs.padded("d", n), bufs.padded("c", n))
        args = (state, cancel, n, jobs, target_cam(T_cam_world, K, near_m),
                target_cam(T_cam_world, K, near_m, np.float64), tile_marks(None, K, 16, "warp ahead"), BAND_ROWS)
        frame = _Frame(views, state, cancel, bufs, args)
        with sh.cv:
            bufs.user = frame
            sh.frame = frame
            if self._thread is None:
                self._thread = threading.Thread(target=_serve, args=(sh,), name="presim-warp-ahead", daemon=True)
                self._thread.start()
            sh.cv.notify_all()

    def take(self, view: Any) -> tuple[np.ndarray, np.ndarray] | None:
        """``view``'s ``(depth_m, color)`` from the thread (= ``filtered_composite_banded`` of its warp; waited for
        while running; valid until the next frame), or None: the loop warps it itself."""
        frame = self._sh.frame
        if frame is None:
            return None
        k = next((i for i, v in enumerate(frame.views) if v is view), -1)
        if k < 0:
            return None
        st = frame.state
        if st[k] == QUEUED:
            st[k] = CLAIMED  # the kernel may have started it this instant: then its buffer is not read
            return None
        while st[k] == RUNNING and not frame.finished:
            pass  # the kernel holds no GIL; a view takes ~0.1-0.3 ms
        if st[k] != DONE:
            return None
        st[k] = CLAIMED
        self.taken += 1
        return frame.bufs.d[k], frame.bufs.c[k]

    def wait(self) -> None:
        """Block until the thread is done with the current frame's views (tests, benchmarks)."""
        sh = self._sh
        with sh.cv:
            while sh.frame is not None and not sh.frame.finished and not sh.closed:
                sh.cv.wait()

    def stop(self) -> None:
        """The loop has ended: claim unbegun jobs, stop the kernel (a running warp finishes, without crack pass)."""
        frame = self._sh.frame
        if frame is not None:
            frame.cancel[0] = 1
            st = frame.state
            st[st == QUEUED] = CLAIMED
