"""Later candidates warped ahead on a helper thread (presim/synthesis/warp_ahead.py)."""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest

from presim.geometry import Intrinsics, invert
from presim.synthesis import warp_ahead as WA
from presim.synthesis.renderer import RenderConfig, Renderer
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


def test_warp_ahead_gives_warp_layers_arrays_and_claims_jobs_it_has_not_begun():
    scene = _scene()
    r = Renderer(scene, RenderConfig())
    views = [r.view_points(i) for i in range(4)]
    T_cw = invert(_target(scene))
    K = Intrinsics.from_fov(40, 30, 60.0)
    wa = WarpAhead()
    with wa._sh.cv:  # the thread cannot begin the frame while this is held
        wa.start(views, T_cw, K, 0.01)
        assert wa.take(views[0]) is None  # queued: claimed, the loop warps it itself
    wa.wait()
    assert wa.take(r.view_points(5)) is None  # not handed over
    for v in views[1:]:
        got = wa.take(v)
        want = warp_layers(v, T_cw, K, 0.01)
        np.testing.assert_array_equal(got.layers.depth_m, want.depth_m)
        np.testing.assert_array_equal(got.layers.color, want.color)
        assert got.depth_m is None
        assert (got.layers.depth_m > 0).sum() > 50
        assert wa.take(v) is None  # taken once
    assert wa.taken == 3
    # the next frame reuses the buffers; a frame the thread has not begun is replaced, not run
    T2 = invert(_target(scene, 3))
    with wa._sh.cv:
        wa.start(views[:2], T_cw, K, 0.01)
        wa.start(views[2:], T2, K, 0.01)
    wa.wait()
    assert wa.take(views[0]) is None
    np.testing.assert_array_equal(wa.take(views[3]).layers.depth_m, warp_layers(views[3], T2, K, 0.01).depth_m)
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
    wa.start([r.view_points(1)], invert(_target(scene, 1)), Intrinsics.from_fov(40, 30, 60.0), 0.01)
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
    import presim.synthesis.renderer as R

    monkeypatch.setattr(R, "WARP_AHEAD_MIN_POINTS", 0)  # the test views are small
    scene = _scene()
    K = Intrinsics.from_fov(48, 36, 60.0)  # one thread per frame (threads.SERIAL_MAX_PIXELS)
    base = _frames(Renderer(scene, RenderConfig(warp_ahead=False, **cfg)), scene, K)
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
    assert r._scratch.ahead.taken == want
    if cfg:
        assert want >= 5
    assert sum(len(f[3]) for f in base) >= 6


def test_warp_ahead_is_off_where_it_cannot_help(monkeypatch):
    """Not with an explicit thread count, in render_batch's threads, with blending, for small views,
    or for frames that draw one view; otherwise this frame's later candidates that the previous
    frame drew."""
    import presim.synthesis.renderer as R

    scene = _scene()
    calls = []

    class Spy(WarpAhead):
        def start(self, views, *args, **kw):
            calls.append(len(views))
            super().start(views, *args, **kw)

    small = Intrinsics.from_fov(48, 36, 60.0)
    orig = WA.WarpAhead
    from presim.synthesis import threads as TH

    calls.clear()
    R.WarpAhead = Spy
    _frames(Renderer(scene, RenderConfig(fixed_views=4)), scene, small, 3)
    assert calls == []  # views of fewer than WARP_AHEAD_MIN_POINTS points
    monkeypatch.setattr(R, "WARP_AHEAD_MIN_POINTS", 0)

    try:
        R.WarpAhead = Spy
        for cfg, serial_max in (({"fixed_views": 4, "threads": 1}, None), ({"fixed_views": 4, "threads": 2}, 0),
                                ({"fixed_views": 4, "blend": True}, None), ({"fixed_views": 4, "warp_ahead": False}, None)):
            calls.clear()
            prev = TH.SERIAL_MAX_PIXELS
            TH.SERIAL_MAX_PIXELS = prev if serial_max is None else serial_max  # 0: above SERIAL_MAX_PIXELS
            try:
                _frames(Renderer(scene, RenderConfig(**cfg)), scene, small, 3)
            finally:
                TH.SERIAL_MAX_PIXELS = prev
            assert calls == [], cfg
        r = Renderer(scene, RenderConfig(fixed_views=4))
        r.render_batch(np.stack([_target(scene, i) for i in range(4)] * 2), small)
        assert calls == []
        got = _frames(r, scene, small, 3)
        assert calls == [len(set(b[3][1:]) & set(a[3])) for a, b in zip(got, got[1:])] and min(calls) >= 1
        calls.clear()
        _frames(Renderer(scene, RenderConfig(fixed_views=1)), scene, small, 3)
        assert calls == []  # one view per frame: nothing to warp ahead
    finally:
        R.WarpAhead = orig
    assert threading.active_count() < 50


def test_frame_mode_chooser_measures_and_keeps_the_faster_way():
    from presim.synthesis.threads import FrameModeChooser

    c = FrameModeChooser(("threads", "ahead"), settle=0, warmup=4, window=5, trim=1, explore_every=10)
    cost = {"threads": 5.0, "ahead": 3.0}
    picks = []
    for _ in range(100):
        m = c.pick()
        picks.append(m)
        c.record(m, cost[m])
    assert picks[:4] == ["ahead", "threads", "ahead", "threads"]  # both tried first, in turn
    assert c.samples()[0] == pytest.approx(np.log(3.0 / 5.0)) and c.best() == "ahead"
    later = picks[4:]
    explored = [i for i, m in enumerate(later) if m == "threads"]
    assert 96 / 15 - 1 <= len(explored) <= 96 / 5 + 1  # one frame in about 10 explores
    assert all(later[i - 1] == later[i + 1] == "ahead" for i in explored if 0 < i < len(later) - 1)
    cost["ahead"] = 9.0  # the machine or the scene changed: the choice follows
    for _ in range(100):
        m = c.pick()
        c.record(m, cost[m])
    assert c.best() == "threads"
    for bad in (("a",), ("a", "a"), ("a", "b", "c")):
        with pytest.raises(ValueError):
            FrameModeChooser(bad)
    c = FrameModeChooser(("threads", "ahead"), settle=4)
    for _ in range(4):  # settling: the first way, untimed
        assert c.pick() == "threads"
        c.record("threads", 1e6)
    assert not c._last and c.pick() == "ahead" and c.pick() == "threads"


@pytest.mark.parametrize("pattern", ["views", "wave"])
@pytest.mark.parametrize("faster", ["threads", "ahead"])
def test_frame_mode_chooser_compares_neighbouring_frames(pattern, faster):
    """Frames along a trajectory cost 1-5x each other (how many views they draw); one way is 15 %
    faster on every frame. Comparing each way's recent frames with the other's (the first chooser)
    picked the slower way on ~20 % of the frames here; neighbouring frames find the faster way on
    all frames but the exploring ones."""
    from presim.synthesis.threads import FrameModeChooser

    if pattern == "views":
        base = [3.0, 3.0, 4.0, 3.0, 4.0, 4.0, 3.0, 5.0, 4.0, 3.0]
    else:
        base = [3.0 + 2.0 * np.sin(2 * np.pi * i / 16) for i in range(16)]
    factor = {"threads": 1.0, "ahead": 1.0}
    factor["ahead" if faster == "threads" else "threads"] = 1.0 / 0.85
    c = FrameModeChooser(("threads", "ahead"), settle=0)
    picks = []
    for i in range(400):
        m = c.pick()
        picks.append(m)
        c.record(m, base[i % len(base)] * factor[m])
    assert picks[100:].count(faster) >= 0.85 * 300
    assert c.best() == faster


def test_mid_size_frames_choose_between_threads_and_warp_ahead(monkeypatch):
    """Frames above SERIAL_MAX_PIXELS (here: all) try both ways and keep the faster; same images."""
    import presim.synthesis.renderer as R
    from presim.synthesis import threads as TH

    monkeypatch.setattr(R, "WARP_AHEAD_MIN_POINTS", 0)
    monkeypatch.setattr(TH, "SERIAL_MAX_PIXELS", 0)
    scene = _scene()
    K = Intrinsics.from_fov(48, 36, 60.0)
    base = _frames(Renderer(scene, RenderConfig(warp_ahead=False, fixed_views=3)), scene, K, 20)
    r = Renderer(scene, RenderConfig(fixed_views=3))
    for a, b in zip(base, _frames(r, scene, K, 20)):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    chooser = r._stream.modes[(48, 36)]
    assert chooser.samples()  # frames of both ways, side by side
    assert r._scratch.ahead.taken > 0


def test_mid_size_frames_without_views_to_warp_ahead_use_all_threads(monkeypatch):
    """A frame with no later view to hand over would leave the helper idle on one thread: it runs on
    all threads and is not timed for the choice (its time says nothing about the other way)."""
    import presim.synthesis.renderer as R
    from presim.synthesis import threads as TH

    monkeypatch.setattr(R, "WARP_AHEAD_MIN_POINTS", 0)
    monkeypatch.setattr(TH, "SERIAL_MAX_PIXELS", 0)
    scene = _scene()
    K = Intrinsics.from_fov(48, 36, 60.0)
    r = Renderer(scene, RenderConfig(fixed_views=1))  # one view per frame: nothing to warp ahead
    _frames(r, scene, K, 14)
    assert r.last.frame_mode == "threads" and not r.last.frame_mode_chosen
    chooser = r._stream.modes[(48, 36)]
    assert chooser._n == 0 and not chooser.samples()
    r = Renderer(scene, RenderConfig(fixed_views=3))
    _frames(r, scene, K, 14)
    assert r.last.frame_mode in ("threads", "ahead") and r.last.frame_mode_chosen
    assert r._stream.modes[(48, 36)]._n >= 10


def test_a_first_view_taken_from_the_thread_is_copied():
    """The first view's image becomes the frame's accumulator: never the thread's buffers (the
    next frames reuse them)."""
    from presim.synthesis.core import ViewImageConfig, Workspace, view_image_numba

    scene = _scene(3)
    r = Renderer(scene, RenderConfig())
    view = r.view_points(1)
    T_cw = invert(_target(scene, 1))
    K = Intrinsics.from_fov(40, 30, 60.0)
    want = view_image_numba(view, T_cw, K, ViewImageConfig(), None, Workspace())
    wa = WarpAhead()
    wa.start([view], T_cw, K, 0.01, crack=True)
    wa.wait()
    got = view_image_numba(view, T_cw, K, ViewImageConfig(), None, Workspace(ahead=wa.take))
    assert wa.taken == 1
    np.testing.assert_array_equal(got.depth_m, want.depth_m)
    np.testing.assert_array_equal(got.color, want.color)
    for buf in wa._sets[0].d + wa._sets[0].c:
        assert not np.shares_memory(got.depth_m, buf) and not np.shares_memory(got.color, buf)
