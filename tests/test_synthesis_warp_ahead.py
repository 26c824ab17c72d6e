"""Later candidates warped ahead on a helper thread (presim/synthesis/warp_ahead.py)."""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest

from presim.geometry import Intrinsics, invert
from presim.synthesis import execution as EX
from presim.synthesis.cracks import filtered_composite_banded
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer
from presim.synthesis.warp import warp_layers
from presim.synthesis.warp_ahead import WarpAhead
from presim.testing import rect_scene as S


def _scene(n: int = 6):
    K = Intrinsics.from_fov(64, 48, 60.0)
    return S.make_scene(S.room_rects(), S.orbit_poses(n, span_m=1.2), K)


def _target(scene, i: int = 2) -> np.ndarray:
    T = scene.T_world_cam[i].copy()
    T[:3, 3] += [0.05, 0.0, 0.1]
    return T


def _banded(view, T_cam_world, K):
    lay = warp_layers(view, T_cam_world, K, 0.01)
    return filtered_composite_banded(lay.depth_m, lay.color)


def test_warp_ahead_gives_the_loops_images_and_claims_jobs_it_has_not_begun():
    scene = _scene()
    r = Renderer(scene, RenderConfig())
    views = [r.view(i) for i in range(4)]
    T_cw = invert(_target(scene))
    K = Intrinsics.from_fov(40, 30, 60.0)
    wa = WarpAhead()
    with wa._sh.cv:  # the thread cannot begin the frame while this is held
        wa.start(views, T_cw, K, 0.01)
        assert wa.take(views[0]) is None  # queued: claimed, the loop warps it itself
    wa.wait()
    assert wa.take(r.view(5)) is None  # not handed over
    for v in views[1:]:
        got = wa.take(v)
        want = _banded(v, T_cw, K)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert (got[0] > 0).sum() > 50
        assert wa.take(v) is None  # taken once
    assert wa.taken == 3
    # the next frame reuses the buffers; a frame the thread has not begun is replaced, not run
    T2 = invert(_target(scene, 3))
    with wa._sh.cv:
        wa.start(views[:2], T_cw, K, 0.01)
        wa.start(views[2:], T2, K, 0.01)
    wa.wait()
    assert wa.take(views[0]) is None
    np.testing.assert_array_equal(wa.take(views[3])[0], _banded(views[3], T2, K)[0])
    wa.stop()
    assert wa.take(views[2]) is not None  # done before the stop: still there
    wa.start([], T_cw, K, 0.01)  # nothing to do: no frame
    wa.close()
    with pytest.raises(RuntimeError, match="closed"):
        wa.start(views, T_cw, K, 0.01)


def test_warp_ahead_thread_ends_with_its_owner():
    scene = _scene(3)
    r = Renderer(scene, RenderConfig())
    wa = WarpAhead()
    wa.start([r.view(1)], invert(_target(scene, 1)), Intrinsics.from_fov(40, 30, 60.0), 0.01)
    wa.wait()
    th = wa._thread
    assert th.is_alive()
    del wa
    gc.collect()
    th.join(timeout=10)
    assert not th.is_alive()


def _frames(r: Renderer, scene, K, n: int = 6):
    out = []
    for i in range(n):
        rgbd = r.render(_target(scene, i % len(scene)), K)
        out.append((rgbd.color, rgbd.depth_m, rgbd.source_view, list(r.last.views)))
    return out


@pytest.mark.parametrize("cfg", [{"fixed_views": 4}, {}])
def test_renderer_images_do_not_depend_on_warp_ahead(cfg, monkeypatch):
    """Same images with the thread, without it, and with every view warped ahead before the loop
    asks (the loop then takes them all: fixed views are drawn in candidate order)."""
    monkeypatch.setattr(EX, "WARP_AHEAD_MIN_POINTS", 0)  # the test views are small
    scene = _scene()
    K = Intrinsics.from_fov(48, 36, 60.0)  # one thread per frame (numba_threads.SERIAL_MAX_PIXELS)
    base = _frames(Renderer(scene, RenderConfig(**cfg), PerfConfig(warp_ahead=False)), scene, K)
    r = Renderer(scene, RenderConfig(**cfg))
    for a, b in zip(base, _frames(r, scene, K)):  # the thread as it runs
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    start = WarpAhead.start

    def start_and_wait(self, *args, **kw):
        start(self, *args, **kw)
        self.wait()

    monkeypatch.setattr(WarpAhead, "start", start_and_wait)
    r = Renderer(scene, RenderConfig(**cfg))
    for a, b in zip(base, _frames(r, scene, K)):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    # frames 2..6 take from the thread the later views they share with (any view of) the frame before
    want = sum(len(set(b[3][1:]) & set(a[3])) for a, b in zip(base, base[1:]))
    assert r.executor._ahead.taken == want
    if cfg:
        assert want >= 5
    assert sum(len(f[3]) for f in base) >= 6


def test_warp_ahead_is_off_where_it_cannot_help(monkeypatch):
    """Not with an explicit thread count, for frames on several threads, with blending, for small
    views, for a stream's first frame, or for frames that draw one view; otherwise this frame's
    later candidates that the stream's previous frame drew."""
    from presim import numba_threads as TH

    scene = _scene()
    calls = []

    class Spy(WarpAhead):
        def start(self, views, *args, **kw):
            calls.append(len(views))
            super().start(views, *args, **kw)

    small = Intrinsics.from_fov(48, 36, 60.0)
    monkeypatch.setattr(EX, "WarpAhead", Spy)
    _frames(Renderer(scene, RenderConfig(fixed_views=4)), scene, small, 3)
    assert calls == []  # views of fewer than WARP_AHEAD_MIN_POINTS points
    monkeypatch.setattr(EX, "WARP_AHEAD_MIN_POINTS", 0)
    for cfg, perf, serial_max in ((RenderConfig(fixed_views=4), PerfConfig(threads=1), None),
                                  (RenderConfig(fixed_views=4), PerfConfig(threads=2), 0),
                                  (RenderConfig(fixed_views=4), PerfConfig(), 0),  # frames above SERIAL_MAX_PIXELS
                                  (RenderConfig(fixed_views=4, blend=True), PerfConfig(), None),
                                  (RenderConfig(fixed_views=4), PerfConfig(warp_ahead=False), None)):
        calls.clear()
        with monkeypatch.context() as m:
            if serial_max is not None:
                m.setattr(TH, "SERIAL_MAX_PIXELS", serial_max)
            _frames(Renderer(scene, cfg, perf), scene, small, 3)
        assert calls == [], (cfg, perf)
    r = Renderer(scene, RenderConfig(fixed_views=4))
    poses = np.stack([_target(scene, i) for i in range(4)])
    r.render_batch(poses, small)
    assert calls == []  # every stream's first frame
    r.render_batch(poses, small)  # each stream again at the same pose: its later views were drawn
    assert calls == [len(v) - 1 for v in r.last.batch_views] and min(calls) >= 1
    calls.clear()
    got = _frames(r, scene, small, 3)
    assert calls == [len(set(b[3][1:]) & set(a[3])) for a, b in zip(got, got[1:])] and min(calls) >= 1
    calls.clear()
    _frames(Renderer(scene, RenderConfig(fixed_views=1)), scene, small, 3)
    assert calls == []  # one view per frame: nothing to warp ahead
    assert threading.active_count() < 50


def test_a_first_view_taken_from_the_thread_is_copied(monkeypatch):
    """The first view's image becomes the frame's accumulator: never the thread's buffers (the
    next frames reuse them); it equals the loop's own view image."""
    from presim.synthesis.pipeline import Workspace, view_image_numba

    monkeypatch.setattr(EX, "WARP_AHEAD_MIN_POINTS", 0)
    scene = _scene(3)
    r = Renderer(scene, RenderConfig())
    view = r.view(1)
    T_cw = invert(_target(scene, 1))
    K = Intrinsics.from_fov(40, 30, 60.0)
    cfg = RenderConfig()
    want = view_image_numba(view, T_cw, K, cfg, None, Workspace())
    ex = EX.Executor(PerfConfig(), cfg)
    assert ex.ahead_possible(K)
    try:
        with ex.frame(K):
            ex.warp_ahead([view], T_cw, K, cfg.near_m)
            ex._ahead.wait()
            got = ex.view_image(view, T_cw, K, cfg, None)
            assert ex._ahead.taken == 1
        np.testing.assert_array_equal(got.depth_m, want.depth_m)
        np.testing.assert_array_equal(got.color, want.color)
        for buf in ex._ahead._sets[0].d + ex._ahead._sets[0].c:
            assert not np.shares_memory(got.depth_m, buf) and not np.shares_memory(got.color, buf)
    finally:
        ex.close()
