"""Batched torch rendering (``backend="torch_batch"``, CPU here) against the per-frame core."""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics, look_at
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S


def _poses():
    return np.stack([look_at((0.1 * k - 0.15, -1.0, 1.25), (0.0, 0.5, 0.4)) for k in range(4)]
                    + [look_at((0.0, -0.8, 1.3), (0.4, 0.5, 0.6))])


@pytest.mark.parametrize("size", [(64, 48), (24, 18)])  # native sampling, and a level-of-detail case
def test_render_batch_equals_per_frame_core(size):
    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    K = Kc.scaled(*size)
    poses = _poses()
    kw = dict(fill_holes=False, hole_dilation_px=0, reuse_move_m=0.0)
    batch = Renderer(scene, RenderConfig(backend="torch_batch", batch_views=3, **kw))
    outs = batch.render_batch(poses, K)
    assert len(outs) == len(poses)
    # Definition: the per-frame core with exactly the first 3 views, later views filling holes only.
    for b in ("torch", "reference"):
        one = Renderer(scene, RenderConfig(backend=b, fixed_views=3, **kw))
        for T, o in zip(poses, outs):
            e = one.render(T, K)
            tol = 0.0 if b == "torch" else 0.01  # float32 vs float64 projection at pixel borders
            assert np.mean(o.valid != e.valid) <= tol, b
            assert np.mean(np.any(o.color != e.color, -1)) <= 2 * tol, b
            assert np.mean(o.source_view != e.source_view) <= 2 * tol, b
            if b == "torch":
                np.testing.assert_array_equal(o.depth_m, e.depth_m)
            assert o.hole_frac_before_fill == pytest.approx(e.hole_frac_before_fill, abs=tol)


def test_render_batch_fills_and_other_backends_loop():
    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    poses = _poses()[:2]
    outs = Renderer(scene, RenderConfig(backend="torch_batch")).render_batch(poses, Kc)
    for o in outs:
        assert o.color.shape == (48, 64, 3) and (o.depth_m > 0).all()  # filled
        assert o.valid.mean() > 0.9
    r = Renderer(scene, RenderConfig())
    loop = r.render_batch(poses, Kc)
    np.testing.assert_array_equal(loop[1].color, Renderer(scene, RenderConfig()).render(poses[1], Kc).color)
    with pytest.raises(ValueError, match="B, 4, 4"):
        r.render_batch(np.eye(4), Kc)


@pytest.mark.parametrize("size", [(64, 48), (256, 192)])  # one thread per frame in render(); two (parallel kernels)
def test_frames_on_threads_equal_render_per_stream(size):
    """numba render_batch on two threads: frame b of every batch equals what render() gives for
    camera stream b (its own renderer, same config, the selection reuse on), at a small size and
    at one whose frames run parallel kernels in render() (serial twins in the batch threads)."""
    from presim.synthesis.threads import SERIAL_MAX_PIXELS

    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    K = Intrinsics.from_fov(*size, 60.0)
    assert (K.width * K.height > SERIAL_MAX_PIXELS) == (size[0] > 64)
    cfg = RenderConfig(batch_threads=2, reuse_move_m=0.02, reuse_turn_deg=2.0, max_zoom=8.0)
    r = Renderer(scene, cfg)
    assert r.batch_threads(5) == 2 and r.batch_threads(1) == 1
    assert Renderer(scene, RenderConfig(backend="reference")).batch_threads(5) == 1
    streams = [Renderer(scene, cfg) for _ in range(5)]
    base = _poses()
    reused = []
    for step in range(3):  # small moves: streams reuse their own previous selection
        poses = base.copy()
        poses[:, 0, 3] += 0.005 * step
        outs = r.render_batch(poses, K)
        assert len(r.last.batch_views) == 5 and r.last.batch_views[-1] == r.last.views
        assert r.last.reused_selection == (step > 0)  # frame 4 continues stream 4, not frame 3
        for b, (T, o) in enumerate(zip(poses, outs)):
            e = streams[b].render(T, K)
            reused.append(streams[b].last.reused_selection)
            np.testing.assert_array_equal(o.color, e.color)
            np.testing.assert_array_equal(o.depth_m, e.depth_m)
            np.testing.assert_array_equal(o.source_view, e.source_view)
            assert r.last.batch_views[b] == streams[b].last.views
    assert sum(reused) >= 5  # the reuse was exercised on the streams
    with pytest.raises(ValueError, match="batch_threads"):
        RenderConfig(batch_threads=-1)


def test_auto_batch_measures_threads_against_frames_one_after_another():
    """batch_threads = 0 (auto) with frames that warp views ahead: the batches alternate between
    the frame threads and one frame after another (with the helper thread) while the chooser
    measures, then keep one way; every frame equals render() of its camera stream either way. A
    frame size without the helper (>= TILED_MIN_PIXELS) always uses the threads."""
    import numba

    from presim.synthesis.composite import TILED_MIN_PIXELS

    assert numba.get_num_threads() >= 2  # the test machine and CI have 2 cores
    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    K = Intrinsics.from_fov(64, 48, 60.0)
    r = Renderer(scene, RenderConfig())
    streams = [Renderer(scene, RenderConfig()) for _ in range(3)]
    base = _poses()[:3]
    modes = []
    for step in range(18):
        poses = base.copy()
        poses[:, 0, 3] += 0.03 * step
        outs = r.render_batch(poses, K)
        modes.append(r.batch_mode)
        for b, (T, o) in enumerate(zip(poses, outs)):
            e = streams[b].render(T, K)
            np.testing.assert_array_equal(o.color, e.color)
            np.testing.assert_array_equal(o.depth_m, e.depth_m)
    assert modes[:10] == ["threads"] * 10  # settling: the first way, untimed
    assert modes[10:16] == ["sequential", "threads"] * 3  # then the ways in turn
    chooser = r._batch_modes[(3, 64, 48)]
    assert len(chooser.samples()) == chooser.warmup - 2  # each batch between two of the other way: one sample
    big = Intrinsics.from_fov(400, 400, 60.0)
    assert big.width * big.height >= TILED_MIN_PIXELS
    r2 = Renderer(scene, RenderConfig(max_zoom=16.0))  # rendered at 400x400 (not at the capture's sampling)
    r2.render_batch(base[:2], big)
    assert r2.batch_mode == "threads" and not r2._batch_modes
