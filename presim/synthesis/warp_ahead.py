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
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, NamedTuple

import numba as nb
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from presim.geometry import Intrinsics
from presim.synthesis.cracks import LOWEST_SET_BIT, banded_crack_kernel, rows_per_band
from presim.synthesis.warp import (CULL_MARGIN, ChunkBounds, LayeredImage, chunk_keep_kernel, target_cam, tile_marks,
                                   warp_layers_kernel)

__all__ = ["WarpAhead", "AheadImage", "MAX_JOBS", "WARP_AHEAD_MIN_POINTS"]

MAX_JOBS = 8
"""At most this many views are handed to the thread per frame (the kernel takes fixed-size tuples:
one compilation)."""

WARP_AHEAD_MIN_POINTS = 10_000
"""Views of fewer points are not handed to the thread: the handover costs the main thread about
what warping such a view does (``start`` took 34 µs alone and 86-107 µs per frame inside
frames, with the two threads' contention; a warp takes ~5-9 ns per point). Not tuned further: the
captures here give 19 200-point views at 128x128 (level 2 of 640x480 frames)."""

QUEUED, RUNNING, DONE, CLAIMED = 0, 1, 2, 3
"""Job states (int32)."""

_warp_serial = warp_layers_kernel.serial
_crack_serial = banded_crack_kernel.serial
_NO_MASK = np.zeros((1, 1), np.bool_)
_FIELDS_KEPT = 2 * MAX_JOBS  # views whose kernel arguments are kept (the view object too: ids stay unique)


@intrinsic
def _store_release(typingctx, arr, idx, val):  # pragma: no cover - compiled into the kernel
    """``arr[idx] = val`` (int32 array) as an atomic store with release order: the writes before it
    are visible to a thread that sees the value."""
    if not isinstance(arr, types.Array) or arr.dtype != types.int32:
        return None

    def codegen(context, builder, signature, args):
        aryty, idxty, valty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [context.cast(builder, args[1], idxty, types.intp)])
        builder.store_atomic(context.cast(builder, args[2], valty, aryty.dtype), ptr, ordering="release", align=4)
        return context.get_dummy_value()

    return types.void(arr, idx, val), codegen


@intrinsic
def _load_acquire(typingctx, arr, idx):  # pragma: no cover - compiled into the kernel
    """``arr[idx]`` (int32 array) as an atomic load with acquire order (read anew each time: the
    other thread may have changed it)."""
    if not isinstance(arr, types.Array) or arr.dtype != types.int32:
        return None

    def codegen(context, builder, signature, args):
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [context.cast(builder, args[1], idxty, types.intp)])
        return builder.load_atomic(ptr, ordering="acquire", align=4)

    return types.int32(arr, idx), codegen


class Jobs(NamedTuple):
    """One frame's jobs: per view (tuples of :data:`MAX_JOBS` entries) its points and chunk bounds,
    and the output buffers."""

    xyz: tuple
    rgb: tuple
    layer_start: tuple
    bounds: tuple
    """:class:`~presim.synthesis.warp.ChunkBounds` per view."""
    zb: tuple
    cb: tuple
    d: tuple
    c: tuple


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _warp_jobs_kernel(state, cancel, n, jobs, cam, cam64, tm, crack, band):  # pragma: no cover
    # Jobs k < n in order: what warp_layers(view k, ...) computes without tiles, on one thread, into
    # zb[k] / cb[k], and with ``crack`` then the crack pass of filtered_composite_banded over the
    # whole image (no replace mask) into d[k] / c[k]. A job not queued any more (claimed by the
    # loop) is skipped; once cancel[0] is set (the frame's loop has ended) nothing more is done.
    for k in range(n):
        if _load_acquire(cancel, 0) != 0:
            return
        if _load_acquire(state, k) != QUEUED:
            continue
        _store_release(state, k, RUNNING)
        b = jobs.bounds[k]
        vis = np.ones(b.lo.shape[1], np.uint8)
        if cam.near > 0 and b.abs_max < np.inf:
            chunk_keep_kernel(b, cam64, CULL_MARGIN, tm, vis)
        # with the crack pass, which reads colour only where the depth is > 0, the colour planes
        # are not cleared
        _warp_serial(jobs.xyz[k], jobs.rgb[k], jobs.layer_start[k], 1, cam, tm, vis, not crack, jobs.zb[k], jobs.cb[k])
        if crack:
            if _load_acquire(cancel, 0) != 0:  # nobody will read it: no crack pass, not done
                _store_release(state, k, CLAIMED)
                return
            _crack_serial(jobs.zb[k], jobs.cb[k], LOWEST_SET_BIT, _NO_MASK, False, _NO_MASK, band, jobs.d[k], jobs.c[k])
        _store_release(state, k, DONE)  # after the images: the loop reads them once it sees DONE


@dataclass(frozen=True)
class AheadImage:
    """A view warped by the thread: its layers, and with ``crack`` its crack-filtered composite
    over the whole image (what :func:`presim.synthesis.composite.filtered_composite_banded` gives
    without a replace mask; None otherwise). The arrays are the thread's buffers: valid until the
    next frame starts."""

    layers: LayeredImage
    depth_m: np.ndarray | None
    color: np.ndarray | None


class _Buffers:
    """One set of per-job output buffers (layers and images), reused by every other frame."""

    def __init__(self) -> None:
        self.zb: list[np.ndarray] = []
        self.cb: list[np.ndarray] = []
        self.d: list[np.ndarray] = []
        self.c: list[np.ndarray] = []
        self.user: _Frame | None = None
        """The last frame that used the set."""

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
    """One frame's jobs: the views, their states, the stop flag, the buffer set and the kernel's
    arguments."""

    views: list[Any]
    state: np.ndarray
    cancel: np.ndarray
    bufs: _Buffers
    crack: bool
    args: tuple
    begun: bool = False
    """The thread has taken the frame (its kernel call runs or has run)."""
    finished: bool = False
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
        # Two buffer sets, one per frame in turn: a new frame does not wait for the thread to end
        # the previous one's last warp (cancelled, it still finishes it).
        self._sets = (_Buffers(), _Buffers())
        self._turn = 0
        self._views: OrderedDict[int, tuple[Any, tuple]] = OrderedDict()  # id -> (view, kernel fields)
        self.taken = 0
        """Views the loop took from the thread."""
        self._finalizer = weakref.finalize(self, _close, self._sh)

    def close(self) -> None:
        """End the thread (after a running kernel call)."""
        self._finalizer()

    def start(self, views: list[Any], T_cam_world: np.ndarray, K: Intrinsics, near_m: float,
              crack: bool = False) -> None:
        """Warp ``views`` (prepared :class:`~presim.synthesis.warp.ViewPoints`, in the order the loop
        will likely want them; at most :data:`MAX_JOBS` are taken) for this target camera, and with
        ``crack`` run the banded crack pass on each (:class:`AheadImage`). The thread begins once
        it has finished the previous frame's running warp (the previous frame's jobs not begun are
        dropped)."""
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
        H, W = K.height, K.width
        bufs.fit(views, H, W)
        n = len(views)
        fields = [self._fields(v) for v in views]
        fields += [fields[0]] * (MAX_JOBS - n)  # fixed-size tuples; jobs >= n are never run
        state = np.full(MAX_JOBS, CLAIMED, np.int32)
        state[:n] = QUEUED
        cancel = np.zeros(1, np.int32)
        jobs = Jobs(*zip(*fields), bufs.padded("zb", n), bufs.padded("cb", n), bufs.padded("d", n), bufs.padded("c", n))
        args = (state, cancel, n, jobs, target_cam(T_cam_world, K, near_m), target_cam(T_cam_world, K, near_m, np.float64),
                tile_marks(None, K, 16, "warp ahead"), bool(crack), int(rows_per_band(H)))
        frame = _Frame(views, state, cancel, bufs, bool(crack), args)
        with sh.cv:
            bufs.user = frame
            sh.frame = frame
            if self._thread is None:
                self._thread = threading.Thread(target=_serve, args=(sh,), name="presim-warp-ahead", daemon=True)
                self._thread.start()
            sh.cv.notify_all()

    def _fields(self, view: Any) -> tuple:
        """The kernel's per-view arguments (xyz, rgb, layer_start, chunk bounds, projective, frame,
        abs max), kept per view object (a view's arrays never change)."""
        got = self._views.get(id(view))
        if got is not None and got[0] is view:
            self._views.move_to_end(id(view))
            return got[1]
        f = (np.ascontiguousarray(view.xyz_world), np.ascontiguousarray(view.rgb),
             np.ascontiguousarray(view.layer_start),
             ChunkBounds(np.ascontiguousarray(view.chunk_lo), np.ascontiguousarray(view.chunk_hi),
                         bool(view.chunk_projective), np.ascontiguousarray(view.chunk_to_world),
                         float(view.chunk_abs_max)))
        self._views[id(view)] = (view, f)
        while len(self._views) > _FIELDS_KEPT:
            self._views.popitem(last=False)
        return f

    def take(self, view: Any) -> AheadImage | None:
        """``view`` warped by the thread (waited for while it works on it), or None when the loop
        must warp it itself (not handed over, not reached yet, or the kernel failed: the loop's own
        warp then raises the error)."""
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
        b = frame.bufs
        lay = LayeredImage(b.zb[k], b.cb[k])
        return AheadImage(lay, b.d[k], b.c[k]) if frame.crack else AheadImage(lay, None, None)

    def wait(self) -> None:
        """Block until the thread is done with the current frame's views (tests, benchmarks)."""
        sh = self._sh
        with sh.cv:
            while sh.frame is not None and not sh.frame.finished and not sh.closed:
                sh.cv.wait()

    def stop(self) -> None:
        """The frame's loop has ended: claim the jobs not begun and tell the kernel to stop (a
        running warp finishes; its crack pass is skipped)."""
        frame = self._sh.frame
        if frame is not None:
            frame.cancel[0] = 1
            st = frame.state
            st[st == QUEUED] = CLAIMED
