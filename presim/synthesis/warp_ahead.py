"""Later candidate views warped on a second thread while the main thread composites (issue 13).

A frame of at most :data:`presim.synthesis.threads.SERIAL_MAX_PIXELS` pixels renders on one numba
thread (parallel regions cost more than they give there), so on a 2-core machine one core idles.
The adaptive loop (:func:`presim.synthesis.core.synthesize_frame`) warps its views one after the
other, and which view comes next depends on the holes the previous ones left. It cannot be known
before the frame, but it can be guessed: a camera that moves a little draws mostly the views its
previous frame drew.

:class:`WarpAhead` owns one helper thread. When a frame starts, the Renderer hands it the later
candidates (2..``max_views``) that the camera stream's previous frame drew too (a camera that moves
a little draws mostly the same views again; handing over the next candidates in order instead
found more of the views the loop then drew but warped twice as many it did not, and a thread
warping views nobody needs slows the main thread's kernels on a shared 2-core machine), provided
their prepared views are cached (at the level of detail this frame picks) and hold at least
:data:`WARP_AHEAD_MIN_POINTS` points. The thread warps them in candidate order, each into buffers
of its own, **in one call of a numba kernel that holds no GIL** (:func:`_warp_jobs_kernel`: per
view the chunk culling and the serial warp kernel of :func:`presim.synthesis.warp.warp_layers`).
A first version called ``warp_layers`` once per view from Python: each call took the GIL back for
~20 µs, and the main thread, which needs the GIL between its own kernels, lost about half of what
the thread saved (apc capture, 128x128: warp 1.0 → 0.35 ms per frame, the other stages +0.25 ms).

Each job has a state in a small int32 array shared by the two threads: queued, running, done,
claimed. When the loop wants a view (:meth:`WarpAhead.take`) and its job is done, it gets the
layers; running, it waits for them (a short spin: the kernel sets the state when the view is
done); queued, it claims the job and warps the view itself as before (the kernel skips claimed
jobs). Both threads may write a state at the same moment; the outcomes are all safe: if the
kernel starts a job the loop has just claimed, the loop warps the view itself and the kernel's
buffer is not read. The kernel stores ``done`` after a memory fence, so the layers are complete
when the loop sees it. When the loop ends, the jobs not started are claimed (:meth:`stop`); a
warp still running finishes on its own and the next frame waits for the kernel before it reuses
the buffers.

The layers do not depend on who warped them: the same kernels with the same view, pose and
intrinsics give the same arrays, and a frame of this size warps its later views fully anyway
(tiles from :data:`presim.synthesis.composite.TILED_MIN_PIXELS` on). The images are therefore
identical with and without the thread (tested); a candidate the loop never draws costs the
second core a warp.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numba as nb
import numpy as np
from numba import types
from numba.extending import intrinsic

from presim.geometry import Intrinsics
from presim.synthesis.warp import (_CULL_MARGIN, _NO_SAT, _NO_TILES, CHUNK_PTS, WARP_BLOCK_PTS, LayeredImage,
                                   _chunk_keep_kernel, _warp_layers_kernel)

__all__ = ["WarpAhead", "MAX_JOBS", "WARP_AHEAD_MIN_POINTS"]

MAX_JOBS = 8
"""At most this many views are handed to the thread per frame (the kernel takes fixed-size tuples:
one compilation)."""

WARP_AHEAD_MIN_POINTS = 10_000
"""Views of fewer points are not handed to the thread: their warp (~5-9 ns per point) takes about
what the handover and the two threads' contention cost the main thread (the sample scene at
128x128 warps 4 800-point views: 1.67 against 1.75 ms per frame with them handed over; the apc
capture's 19 200-point views: 3.0 against 2.7 ms)."""

QUEUED, RUNNING, DONE, CLAIMED = 0, 1, 2, 3
"""Job states (int32)."""

_warp_serial = _warp_layers_kernel.serial


@intrinsic
def _fence(typingctx):  # pragma: no cover - compiled into the kernel
    """A full memory fence (stores before it are visible to other threads before stores after it)."""
    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return types.void(), codegen


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _warp_jobs_kernel(state, n, xyz, rgb, layer_start, lo, hi, projective, S, A, M, fx, fy, cx, cy, near, W, H,
                      zb, cb):  # pragma: no cover
    # Jobs k < n in order: what warp_layers(view k, ...) computes without tiles, on one thread, into
    # zb[k] / cb[k]; a job not queued any more (claimed by the loop) is skipped.
    fx32 = np.float32(fx)
    fy32 = np.float32(fy)
    cx32 = np.float32(cx)
    cy32 = np.float32(cy)
    near32 = np.float32(near)
    for k in range(n):
        if state[k] != QUEUED:
            continue
        state[k] = RUNNING
        vis = np.ones(lo[k].shape[1], np.uint8)
        if near > 0 and A[k] < np.inf:
            _chunk_keep_kernel(lo[k], hi[k], projective[k], M, S[k], A[k], np.float64(fx32), np.float64(fy32),
                               np.float64(cx32), np.float64(cy32), np.float64(near32), W, H, _CULL_MARGIN, _NO_SAT,
                               16, False, vis)
        _warp_serial(xyz[k], rgb[k], layer_start[k], 1, M, fx32, fy32, cx32, cy32, near32, _NO_TILES, False, 16,
                     _NO_TILES.reshape(-1), vis, CHUNK_PTS, WARP_BLOCK_PTS, zb[k], cb[k])
        _fence()  # the layers are written before the state says so
        state[k] = DONE
        _fence()


class _Frame:
    def __init__(self, views: list[Any], state: np.ndarray, args: tuple):
        self.views = views
        self.state = state
        self.args = args
        self.begun = False
        """The thread has taken the frame (its kernel call runs or has run)."""
        self.finished = False
        """The kernel call has returned (or failed)."""


class _Shared:
    """What the thread shares with its :class:`WarpAhead` (not the object itself: the thread must
    not keep it alive; when it is collected, the thread is told to end)."""

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.frame: _Frame | None = None
        self.closed = False


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
    """One helper thread that warps a frame's later candidate views ahead of the adaptive loop
    (see the module doc). For one rendering thread (each Renderer scratch has its own); the thread
    starts on the first :meth:`start` and ends when this object is collected or :meth:`close` d."""

    def __init__(self) -> None:
        self._sh = _Shared()
        self._thread: threading.Thread | None = None
        self._zb: list[np.ndarray] = []
        self._cb: list[np.ndarray] = []
        self.taken = 0
        """Views the loop took from the thread."""
        self._finalizer = weakref.finalize(self, _close, self._sh)

    def close(self) -> None:
        """End the thread (after a running kernel call)."""
        self._finalizer()

    def start(self, views: list[Any], T_cam_world: np.ndarray, K: Intrinsics, near_m: float) -> None:
        """Warp ``views`` (prepared :class:`~presim.synthesis.warp.ViewPoints`, in the order the loop
        will likely want them; at most :data:`MAX_JOBS` are taken) for this target camera. Waits for
        the previous frame's kernel when it still runs (its buffers are reused)."""
        views = list(views)[:MAX_JOBS]
        if not views:
            return
        sh = self._sh
        with sh.cv:
            if sh.closed:
                raise RuntimeError("WarpAhead: closed")
            while sh.frame is not None and sh.frame.begun and not sh.frame.finished:
                sh.cv.wait()
            sh.frame = None  # a frame the thread has not begun is dropped
        H, W = K.height, K.width
        for k, v in enumerate(views):
            shape = (v.num_layers, H, W)
            if k == len(self._zb):
                self._zb.append(np.empty(shape, np.float32))
                self._cb.append(np.empty(shape + (3,), np.uint8))
            elif self._zb[k].shape != shape:
                self._zb[k] = np.empty(shape, np.float32)
                self._cb[k] = np.empty(shape + (3,), np.uint8)
        n = len(views)
        pad = views + [views[0]] * (MAX_JOBS - n)  # fixed-size tuples; jobs >= n are never run

        def tup(get):
            return tuple(np.ascontiguousarray(get(v)) for v in pad)

        M = np.ascontiguousarray(np.asarray(T_cam_world, np.float64)[:3, :4], np.float32)
        zb = tuple(self._zb[k] for k in range(n)) + (self._zb[0],) * (MAX_JOBS - n)
        cb = tuple(self._cb[k] for k in range(n)) + (self._cb[0],) * (MAX_JOBS - n)
        state = np.full(MAX_JOBS, CLAIMED, np.int32)
        state[:n] = QUEUED
        args = (state, n, tup(lambda v: v.xyz_world), tup(lambda v: v.rgb), tup(lambda v: v.layer_start),
                tup(lambda v: v.chunk_lo), tup(lambda v: v.chunk_hi),
                tuple(bool(v.chunk_projective) for v in pad), tup(lambda v: v.chunk_to_world),
                tuple(float(v.chunk_abs_max) for v in pad), M, float(K.fx), float(K.fy), float(K.cx),
                float(K.cy), float(near_m), int(W), int(H), zb, cb)
        with sh.cv:
            sh.frame = _Frame(views, state, args)
            if self._thread is None:
                self._thread = threading.Thread(target=_serve, args=(sh,), name="presim-warp-ahead", daemon=True)
                self._thread.start()
            sh.cv.notify_all()

    def take(self, view: Any) -> LayeredImage | None:
        """The layers of ``view`` warped by the thread (waited for while it warps them), or None
        when the loop must warp it itself (not handed over, not reached yet, or the kernel failed:
        the loop's own warp then raises the error)."""
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
        return LayeredImage(self._zb[k], self._cb[k])

    def wait(self) -> None:
        """Block until the thread is done with the current frame's views (tests, benchmarks)."""
        sh = self._sh
        with sh.cv:
            while sh.frame is not None and not sh.frame.finished and not sh.closed:
                sh.cv.wait()

    def stop(self) -> None:
        """Claim the jobs not started (the frame's loop has ended); a running warp finishes."""
        frame = self._sh.frame
        if frame is not None:
            st = frame.state
            st[st == QUEUED] = CLAIMED
