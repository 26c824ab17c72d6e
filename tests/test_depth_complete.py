"""Depth completion (presim.depth.complete) and the renderer's completion pass: answers known on paper
(a plane continued exactly, a colour edge respected, free-space violations rejected), numba against the
reference, the scene round trip and the rendered holes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from presim.capture.store import load_scene, save_scene
from presim.depth.complete import (CompleteConfig, check_completion, check_completion_ref, complete_frame,
                                   complete_frame_ref, complete_scene_depth, completion_neighbours)
from presim.geometry import Intrinsics, look_at
from presim.synthesis.config import PerfConfig, RenderConfig
from presim.synthesis.renderer import Renderer
from presim.testing.rect_scene import Rect, make_scene, raycast, room_rects

K = Intrinsics(48.0, 48.0, 31.5, 23.5, 64, 48)
SMALL = CompleteConfig(max_dist_px=200.0, radius_px=40, step_px=6, slope_ridge=0.0)  # radius 4, step 1 at 64 px


def _tilted_plane(K: Intrinsics) -> np.ndarray:
    """z-depth of the plane 0.2 x + 0.3 y + z = 2 (camera frame): 1/z affine in the pixel coordinates."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    return (2.0 / (0.2 * (u - K.cx) / K.fx + 0.3 * (v - K.cy) / K.fy + 1.0)).astype(np.float32)


def test_plane_continued_exactly_numba_and_reference():
    truth = _tilted_plane(K)
    depth = truth.copy()
    depth[:8] = 0  # the sensor's empty top rows
    depth[:, -5:] = 0
    color = np.full((K.height, K.width, 3), 120, np.uint8)
    for fn in (complete_frame, complete_frame_ref):
        out = fn(depth, color, SMALL)
        filled = depth == 0
        assert (out[filled] > 0).all(), fn.__name__
        assert (out[~filled] == 0).all()
        np.testing.assert_allclose(out[filled], truth[filled], rtol=2e-4)


def test_colour_edge_keeps_each_surface():
    # left half near (1 m, red), right half far (3 m, green); the top band empty over both
    depth = np.where(np.arange(K.width)[None, :] < 32, 1.0, 3.0).astype(np.float32).repeat(K.height, 0)
    color = np.zeros((K.height, K.width, 3), np.uint8)
    color[:, :32] = (200, 30, 30)
    color[:, 32:] = (30, 200, 30)
    depth[:10] = 0
    out = complete_frame(depth, color, SMALL)
    np.testing.assert_allclose(out[:10, :32], 1.0, rtol=1e-3)
    np.testing.assert_allclose(out[:10, 32:], 3.0, rtol=1e-3)
    np.testing.assert_allclose(complete_frame_ref(depth, color, SMALL), out, rtol=1e-4)


def test_check_votes_and_free_space():
    rects = [Rect((-5, -5, 2.0), (10, 0, 0), (0, 10, 0), checker_m=0.25)]
    T0, T1 = np.eye(4), np.eye(4)
    T1[0, 3] = 0.25  # 6 px of parallax at 2 m
    c0, d0 = raycast(rects, T0, K)
    c1, d1 = raycast(rects, T1, K)
    g = lambda c: c.mean(axis=2).astype(np.float32)  # noqa: E731
    comp = np.zeros_like(d0)
    comp[20:28, 20:28] = d0[20:28, 20:28]  # the true plane: seen and alike in view 1
    comp[30:34, 10:14] = 1.5  # in front of the plane: view 1 sees the plane behind it -> rejected
    args = (g(c0), K, T0, g(c1)[None], d1[None], [K], T1[None])
    for fn in (check_completion, check_completion_ref):
        conf = fn(comp, *args, SMALL)
        assert (conf[20:28, 20:28] == 1.0).all(), fn.__name__
        assert (conf[30:34, 10:14] == 0.0).all()
        assert (conf[comp == 0] == 0).all()
    # a view without depth there still votes by colour; no view at all: unseen confidence
    conf = check_completion(comp, g(c0), K, T0, g(c1)[None], np.zeros_like(d1)[None], [K], T1[None], SMALL)
    assert (conf[20:28, 20:28] == 1.0).all()
    conf = check_completion(comp, g(c0), K, T0, np.zeros((0,) + d0.shape, np.float32),
                            np.zeros((0,) + d0.shape, np.float32), [], np.zeros((0, 4, 4)), SMALL)
    assert (conf[comp > 0] == SMALL.unseen_confidence).all()


def test_check_numba_matches_reference_on_a_room():
    poses = np.stack([look_at((x, -1.0, 1.3), (0.0, 0.5, 0.4)) for x in (-0.2, 0.0, 0.2)])
    scene = make_scene(room_rects(), poses, K)
    d0 = scene.frames.load(1)[1].copy()
    d0[:12] = 0
    comp = complete_frame(d0, scene.frames.load(1)[0], SMALL)
    grey = lambda i: scene.frames.load(i)[0].mean(axis=2).astype(np.float32)  # noqa: E731
    args = (grey(1), K, poses[1], np.stack([grey(0), grey(2)]),
            np.stack([scene.frames.load(i)[1] for i in (0, 2)]), [K, K], poses[[0, 2]], SMALL)
    np.testing.assert_array_equal(check_completion(comp, *args), check_completion_ref(comp, *args))


def test_neighbours_and_config_errors():
    poses = np.stack([look_at((x, 0.0, 0.0), (x, 0.0, 2.0)) for x in (0.0, 0.1, 0.5, 0.05)])
    assert completion_neighbours(poses, 0, range(4), 2) == [3, 1]
    assert completion_neighbours(poses, 0, [0], 2) == []
    with pytest.raises(ValueError, match="max_dist_px"):
        CompleteConfig(max_dist_px=float("nan"))
    with pytest.raises(ValueError, match="min_confidence"):
        CompleteConfig(min_confidence=2.0)
    with pytest.raises(ValueError, match="colour"):
        complete_frame(np.zeros((4, 4), np.float32), np.zeros((4, 5, 3), np.uint8))


def _room_with_empty_top(tmp_path):
    poses = np.stack([look_at((x, -1.0, 1.3), (0.0, 0.5, 0.4)) for x in np.linspace(-0.3, 0.3, 5)])
    scene = make_scene(room_rects(), poses, K)
    colors = np.stack([scene.frames.load(i)[0] for i in range(len(scene))])
    depths = np.stack([scene.frames.load(i)[1] for i in range(len(scene))])
    depths[:, :10] = 0  # the sensor misses the top rows of every frame
    from presim.capture.scene import ArrayFrameSource

    return dataclasses.replace(scene, frames=ArrayFrameSource(colors, depths)), poses


def test_renderer_fills_holes_from_completed_depth_and_keeps_measured_pixels(tmp_path, monkeypatch):
    from presim.synthesis import pipeline

    scene, poses = _room_with_empty_top(tmp_path)
    comp = complete_scene_depth(scene, config=SMALL)
    assert (comp[:, :10] > 0).mean() > 0.8 and (comp[:, 10:] == 0).all()
    target = look_at((0.05, -1.1, 1.35), (0.0, 0.5, 0.6))  # looks higher: the empty band is in view
    base = Renderer(scene, RenderConfig(use_completed_depth=True)).render(target, K)  # no completion in the scene
    withc = dataclasses.replace(scene, depth_completed=comp)
    off = Renderer(withc, RenderConfig(use_completed_depth=False)).render(target, K)
    on = Renderer(withc, RenderConfig()).render(target, K)
    np.testing.assert_array_equal(base.color, off.color)
    assert (~on.valid).mean() < 0.5 * (~off.valid).mean(), ((~on.valid).mean(), (~off.valid).mean())
    np.testing.assert_array_equal(on.color[off.valid], off.color[off.valid])  # measured depth always wins
    truth_c, truth_d = raycast(room_rects(), target, K)
    new = on.valid & ~off.valid
    assert np.median(np.abs(on.depth_m[new] - truth_d[new]) / truth_d[new]) < 0.02
    err = lambda img: np.abs(img.color[new].astype(float) - truth_c[new]).mean()  # noqa: E731
    assert err(on) < err(off)
    # what completion left is filled by pull-push under "auto" (RenderConfig.fill_method); without
    # completion "auto" picks by hole fraction
    methods = []
    fill = pipeline.fill_holes
    monkeypatch.setattr(pipeline, "fill_holes", lambda *a, **k: methods.append(a[3]) or fill(*a, **k))
    for sc, cfg in ((withc, RenderConfig()), (withc, RenderConfig(fill_method="telea")), (withc, RenderConfig(use_completed_depth=False))):
        Renderer(sc, cfg).render(target, K)
    assert methods == ["pushpull", "telea", "auto"]
    tor = Renderer(withc, RenderConfig(), PerfConfig(backend="torch", torch_device="cpu")).render(target, K)
    assert (~tor.valid).mean() < 0.5 * (~off.valid).mean()  # the torch backend runs the stage too
    # the scene folder keeps it (memory-mapped), and a wrong shape is named
    path = save_scene(withc, tmp_path / "room")
    loaded = load_scene(path)
    np.testing.assert_array_equal(np.asarray(loaded.depth_completed), comp)
    np.save(path / "depth_completed.npy", np.zeros((2, 3, 4), np.float32))
    with pytest.raises(ValueError, match="depth_completed.npy"):
        load_scene(path)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_splat_into_holes_matches_reference(backend):
    from presim.synthesis.completion import CompletedPoints, Target, splat_into_holes, splat_into_holes_ref

    rng = np.random.default_rng(3)
    T = look_at((0.0, 0.0, 0.0), (0.0, 0.2, 2.0))
    pts = []
    for v in range(3):  # quantised depths: ties between views and within a view
        xyz = np.stack([rng.uniform(-1.2, 1.2, 3000), rng.uniform(-1.0, 1.4, 3000),
                        np.round(rng.uniform(1.5, 2.5, 3000), 1)], 1).astype(np.float32)
        pts.append(CompletedPoints(10 + v, xyz, rng.integers(0, 255, (3000, 3), dtype=np.uint8)))
    holes = (rng.random((K.height, K.width)) < 0.6).astype(np.uint8)

    def run(fn):
        t = Target(np.ones((K.height, K.width), np.float32), np.full((K.height, K.width, 3), 7, np.uint8),
                   np.full((K.height, K.width), 2, np.int32), holes.copy())
        return fn(pts, T, K, 1e-3, t), t

    n_ref, ref = run(splat_into_holes_ref)
    if backend == "numba":
        n, got = run(splat_into_holes)
    else:
        torch_kernels = pytest.importorskip("presim.synthesis.torch_kernels")
        n, got = run(lambda *a: torch_kernels.splat_into_holes_torch(*a, device="cpu"))
    assert 0 < n_ref < holes.sum() and n == n_ref
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)
    assert ((ref.holes == 0) | (holes != 0)).all() and (ref.depth_m[holes == 0] == 1).all()  # only holes written


def test_the_ring_covers_what_the_local_group_never_saw():
    """Ten views beside the target look at the back wall; two views further away see the left wall the target
    turns to. The ring (RenderConfig.hole_candidates) draws those into the region no near view saw, once the
    completion stage ran; a scene without completed depth renders as without the ring."""
    near = [look_at((x, -1.0, 1.3), (x, 1.5, 1.0)) for x in np.linspace(-0.1, 0.1, 10)]
    far = [look_at((0.3, -0.3, 1.3), (-2.0, 0.3 + 0.2 * k, 1.0)) for k in range(2)]
    poses = np.stack(near + far)
    scene = make_scene(room_rects(), poses, K)
    colors = np.stack([scene.frames.load(i)[0] for i in range(len(scene))])
    truth = np.stack([scene.frames.load(i)[1] for i in range(len(scene))])
    depths = truth.copy()
    depths[:, :4] = 0  # the sensor misses the top rows: the completion stage has something to do
    from presim.capture.scene import ArrayFrameSource

    plain = dataclasses.replace(scene, frames=ArrayFrameSource(colors, depths))
    withc = dataclasses.replace(plain, depth_completed=np.where(depths > 0, 0, truth).astype(np.float32))
    target = look_at((0.0, -1.0, 1.3), (-1.2, 1.2, 1.0))  # turned to the back-left corner
    r_off = Renderer(withc, RenderConfig(hole_candidates=0))
    off = r_off.render(target, K)
    r_on = Renderer(withc, RenderConfig())
    on = r_on.render(target, K)
    assert set(r_off.last.views) <= set(range(10)) and set(r_on.last.views) & {10, 11}
    assert (~on.valid).mean() < 0.5 * (~off.valid).mean(), ((~on.valid).mean(), (~off.valid).mean())
    np.testing.assert_array_equal(on.color[off.valid], off.color[off.valid])  # the ring writes holes only
    truth_c, _ = raycast(room_rects(), target, K)
    new = on.valid & ~off.valid
    err = lambda img: np.abs(img.color[new].astype(float) - truth_c[new]).mean()  # noqa: E731
    assert err(on) < 0.5 * err(off), (err(on), err(off))
    r_t = Renderer(withc, RenderConfig(), PerfConfig(backend="torch", torch_device="cpu"))
    assert (~r_t.render(target, K).valid).mean() < 0.5 * (~off.valid).mean()  # the torch backend draws it too
    # no completed depth: no ring
    a = Renderer(plain, RenderConfig()).render(target, K)
    b = Renderer(plain, RenderConfig(hole_candidates=0)).render(target, K)
    np.testing.assert_array_equal(a.color, b.color)
