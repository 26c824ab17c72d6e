"""Renderer.render_batch: frame b of a batch continues camera stream b."""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics, look_at
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S


def _poses():
    return np.stack([look_at((0.1 * k - 0.15, -1.0, 1.25), (0.0, 0.5, 0.4)) for k in range(4)]
                    + [look_at((0.0, -0.8, 1.3), (0.4, 0.5, 0.6))])


def test_render_batch_equals_render_and_checks_its_poses():
    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    poses = _poses()[:2]
    r = Renderer(scene, RenderConfig())
    loop = r.render_batch(poses, Kc)
    assert len(loop) == 2
    for o in loop:
        assert o.color.shape == (48, 64, 3) and (o.depth_m > 0).all()  # filled
        assert o.valid.mean() > 0.9
    np.testing.assert_array_equal(loop[1].color, Renderer(scene, RenderConfig()).render(poses[1], Kc).color)
    assert r.render_batch(np.zeros((0, 4, 4)), Kc) == []
    with pytest.raises(ValueError, match="B, 4, 4"):
        r.render_batch(np.eye(4), Kc)


@pytest.mark.parametrize("size", [(64, 48), (256, 192)])  # one thread per frame; all threads (parallel kernels)
def test_batch_frames_equal_render_per_stream(size):
    """render_batch: frame b of every batch equals what render() gives for camera stream b (its own
    renderer, same config, the selection reuse on), at a small size (one thread, views warped
    ahead) and at one whose frames run parallel kernels."""
    from presim.numba_threads import SERIAL_MAX_PIXELS

    Kc = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), Kc)
    K = Intrinsics.from_fov(*size, 60.0)
    assert (K.width * K.height > SERIAL_MAX_PIXELS) == (size[0] > 64)
    cfg = RenderConfig(reuse_move_m=0.02, reuse_turn_deg=2.0, max_zoom=8.0)
    r = Renderer(scene, cfg)
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
