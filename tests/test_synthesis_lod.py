"""Level of detail (depth-aware pooling pyramid), temporal selection reuse and the time budget."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from presim.geometry import Intrinsics, invert, look_at, make_pose, project, transform_points, unproject_depth
from presim.imaging.pool import pool_depth_aware, pool_depth_aware_ref
from presim.numba_threads import serial_kernels
from presim.synthesis.lod import LodConfig, build_level, choose_level, footprint_ratio, half_intrinsics
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S


def test_pool_known_block_values():
    d = np.array([[1.0, 1.01, 0.0, 0.0],
                  [2.0, 0.0, 0.0, 3.0]], np.float32)
    c = np.zeros((2, 4, 3), np.uint8)
    c[0, 0] = (10, 20, 30)
    c[0, 1] = (21, 40, 61)  # same surface as (0, 0): averaged, .5 rounds up
    c[1, 0] = (255, 255, 255)  # 2 m: background behind the 1 m surface, ignored
    c[1, 3] = (7, 8, 9)
    pd, pc = pool_depth_aware(d, c, 0.02)
    assert pd.shape == (1, 2) and pc.shape == (1, 2, 3)
    assert pd[0, 0] == pytest.approx(1.005) and tuple(pc[0, 0]) == (16, 30, 46)
    assert pd[0, 1] == 3.0 and tuple(pc[0, 1]) == (7, 8, 9)  # one valid pixel: itself
    pd, pc = pool_depth_aware(np.zeros((2, 2), np.float32), np.full((2, 2, 3), 99, np.uint8))
    assert pd[0, 0] == 0 and (pc == 0).all()  # no valid pixel -> empty


def test_pool_numba_matches_reference_exactly():
    rng = np.random.default_rng(3)
    d = rng.uniform(0.5, 3.0, (37, 50)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = 0.0
    d[5:9, 10:20] = 1.0 + rng.uniform(0, 0.03, (4, 10)).astype(np.float32)  # near-ties within the band
    c = rng.integers(0, 256, (37, 50, 3), dtype=np.uint8)
    bad = rng.random(d.shape)
    d[bad < 0.04] = np.nan  # non-finite and negative depths: invalid, as in the reference
    d[(bad >= 0.04) & (bad < 0.07)] = np.inf
    d[(bad >= 0.07) & (bad < 0.08)] = -np.inf
    d[(bad >= 0.08) & (bad < 0.09)] = -1.0
    d[20:22, 0:2] = np.inf  # a block of +inf only: empty
    counts = set()
    for tol in (0.0, 0.02, 0.5):
        b_d, b_c = pool_depth_aware_ref(d, c, tol)
        for serial in (False, True):
            with serial_kernels(serial):
                a_d, a_c = pool_depth_aware(d, c, tol)
            np.testing.assert_array_equal(a_d, b_d)
            np.testing.assert_array_equal(a_c, b_c)
        blocks = d[:36, :50].reshape(18, 2, 25, 2).transpose(0, 2, 1, 3).reshape(18, 25, 4)
        ok = np.isfinite(blocks) & (blocks > 0)
        dmin = np.where(ok, blocks, np.inf).min(-1, keepdims=True)
        counts |= set(np.unique((ok & (blocks <= dmin.astype(np.float64) * (1 + tol))).sum(-1)).tolist())
    assert b_d[10, 0] == 0 and (b_c[10, 0] == 0).all()
    assert counts == {0, 1, 2, 3, 4}  # blocks averaging 1, 2, 3 and 4 pixels all met


def test_half_intrinsics_places_pooled_points_on_the_surface():
    """A fronto-parallel plane pooled twice: every pooled point is on the plane and projects to the
    centre of its 4x4 source block (source coordinate 4j + 1.5)."""
    K = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    d = np.full((48, 64), 2.0, np.float32)
    c = np.zeros((48, 64, 3), np.uint8)
    _, d2, K2 = build_level(c, d, K, 2)
    assert (K2.width, K2.height) == (16, 12) and K2.fx == 25.0
    assert K2 == half_intrinsics(half_intrinsics(K)) and K2.cx == (31.5 - 0.5) / 2 / 2 - 0.25
    pts, _ = unproject_depth(K2, d2)
    np.testing.assert_allclose(pts[:, 2], 2.0)
    uv, _ = project(K, pts.astype(np.float64))
    jj, ii = np.meshgrid(np.arange(16), np.arange(12))
    np.testing.assert_allclose(uv[:, 0], 4 * jj.reshape(-1) + 1.5, atol=1e-4)
    np.testing.assert_allclose(uv[:, 1], 4 * ii.reshape(-1) + 1.5, atol=1e-4)


def test_choose_level_and_footprint_ratio():
    cfg = LodConfig(levels=3, max_footprint=1.0)
    assert choose_level(1.0, cfg) == 0
    assert choose_level(0.4, cfg) == 1  # 256 px wide from 640: 0.8 px per level-1 point
    assert choose_level(0.2, cfg) == 2  # 128 from 640
    assert choose_level(0.01, cfg) == 3  # capped by levels
    assert choose_level(float("nan"), cfg) == 0
    assert choose_level(0.2, LodConfig(levels=0)) == 0
    # Same camera, target focal 1/5 of the source: the ratio is exactly 0.2.
    T = look_at((0.0, 0.0, 1.0), (0.0, 3.0, 1.0))
    pts = transform_points(T, np.array([[0.1, 0.2, 2.0], [-0.3, 0.0, 4.0], [0.0, 0.1, 3.0]]))
    assert footprint_ratio(pts, invert(T), 500.0, invert(T), 100.0) == pytest.approx(0.2)
    # Target twice as far from the points (moved back along its axis by the points' depth ... ): z_t > z_s
    T_back = T @ make_pose(np.eye(3), (0.0, 0.0, -3.0))
    r = footprint_ratio(pts, invert(T), 500.0, invert(T_back), 500.0)
    assert r == pytest.approx(np.median(np.array([2.0, 4.0, 3.0]) / np.array([5.0, 7.0, 6.0])))
    # With the target intrinsics only points inside the target image count: two points in front of the
    # target but outside its 60 deg image (x / z_t = 3 / 3.5 and 4 / 3.5 > tan 30 deg), with the small
    # ratio 0.5 / 3.5, move the median of all five to 2 / 5 and are ignored with K_tgt.
    K = Intrinsics.from_fov(100, 100, 60.0)
    side = transform_points(T, np.array([[3.0, 0.0, 0.5], [4.0, 0.0, 0.5]]))
    both = np.vstack([pts, side])
    assert footprint_ratio(both, invert(T), 500.0, invert(T_back), 500.0) == pytest.approx(2.0 / 5.0)
    assert footprint_ratio(both, invert(T), 500.0, invert(T_back), 500.0, K_tgt=K) == pytest.approx(r)
    assert np.isnan(footprint_ratio(side, invert(T), 500.0, invert(T_back), 500.0, K_tgt=K))


def _scene(K):
    return S.make_scene(S.room_rects(), S.orbit_poses(4), K)


def test_renderer_lod_keeps_native_size_and_coarsens_small_targets():
    K = Intrinsics.from_fov(160, 120, 60.0)
    scene = _scene(K)
    T = look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4))
    on, off = Renderer(scene, RenderConfig()), Renderer(scene, RenderConfig(lod_levels=0))
    a, b = on.render(T, K), off.render(T, K)
    assert set(on.last.lod_levels) == {0}  # same sampling as the capture: unchanged output
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    Ks = K.scaled(40, 30)  # 1/4 of the capture's focal length
    a, b = on.render(T, Ks), off.render(T, Ks)
    assert min(on.last.lod_levels) >= 1  # level 2 for views as far as the target, 1 for nearer ones
    # Against the exact image (ray-cast at 4x and area-averaged: what a 40x30 camera integrates),
    # the pooled levels are at least as good as point-sampling every point (they average texture
    # instead of aliasing it), with no more holes.
    gt, _ = S.raycast(S.room_rects(), T, K.scaled(160, 120))
    gt = cv2.resize(gt, (40, 30), interpolation=cv2.INTER_AREA)

    def psnr(x):
        return 10 * np.log10(255.0**2 / np.mean((x.astype(float) - gt) ** 2))

    assert psnr(a.color) >= psnr(b.color) - 0.2, (psnr(a.color), psnr(b.color))
    assert a.hole_frac_before_fill <= b.hole_frac_before_fill + 0.01
    assert np.abs(a.depth_m - b.depth_m)[a.valid & b.valid].mean() < 0.02
    pts_full = sum(len(on.view(v).xyz_world) for v in on.last.views)
    pts_lod = sum(on.view(v, k).xyz_world.shape[0] for v, k in zip(on.last.views, on.last.lod_levels))
    assert pts_lod <= pts_full / 3  # 1/4 (level 1) or 1/16 (level 2) of the pixels


def test_temporal_reuse_of_the_selection():
    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = _scene(K)
    T = look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4))
    r = Renderer(scene, RenderConfig())
    first = r.render(T, K)
    assert not r.last.reused_selection
    sel = r.last.selection
    T2 = T.copy()
    T2[:3, 3] += (0.005, 0.0, 0.0)
    r.render(T2, K)
    assert r.last.reused_selection and r.last.selection is sel
    r.render(T, K)  # back at the first pose: same selection, same image
    np.testing.assert_array_equal(r.render(T, K).color, first.color)
    T3 = T.copy()
    T3[:3, 3] += (0.05, 0.0, 0.0)
    r.render(T3, K)
    assert not r.last.reused_selection
    r.render(look_at((0.1, -1.0, 1.25), (0.3, 0.5, 0.4)), K)  # turned > 1 degree
    assert not r.last.reused_selection
    r.render(T3, Intrinsics.from_fov(32, 24, 60.0))  # other intrinsics
    assert not r.last.reused_selection
    r0 = Renderer(scene, RenderConfig(reuse_move_m=0.0))
    r0.render(T, K)
    r0.render(T, K)
    assert not r0.last.reused_selection


def test_time_budget_stops_the_adaptive_loop():
    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = _scene(K)
    T = look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4))
    free = Renderer(scene, RenderConfig(fill_holes=False, stop_hole_frac=0.0)).render(T, K)
    r = Renderer(scene, RenderConfig(fill_holes=False, stop_hole_frac=0.0, time_budget_ms=1e-6))
    out = r.render(T, K)
    assert len(r.last.views) == 1  # the first view always; no time left for a second
    assert out.hole_frac_before_fill >= free.hole_frac_before_fill
    with pytest.raises(ValueError, match="time_budget_ms"):
        RenderConfig(time_budget_ms=-1)
    with pytest.raises(ValueError, match="lod_levels"):
        RenderConfig(lod_levels=9)
