"""Depth refinement (thesis §3.4.1) on analytic two-plane scenes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from presim.depth.refine import RefineConfig, RefView, refine_depth, select_reference_views
from presim.testing.two_planes import render_two_planes, two_plane_poses
from presim.geometry import Intrinsics, make_pose


def _views(width: int, height: int, n: int, baseline_m: float = 0.06):
    K = Intrinsics.from_fov(width, height, 60.0)
    poses = two_plane_poses(n, baseline_m)
    views = [render_two_planes(T, K) for T in poses]
    refs = [RefView(c, d, K, T) for (c, d), T in zip(views[1:], poses[1:])]
    return K, poses, views, refs


def _corrupt(gt: np.ndarray, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    H, W = gt.shape
    raw = np.roll(gt, 3, axis=1)          # depth misaligned with color by 3 px (edge bleeding)
    raw[:, :3] = gt[:, :3]
    raw[int(0.33 * H):int(0.45 * H), int(0.12 * W):int(0.22 * W)] = 0          # missing depth
    raw[int(0.66 * H):int(0.75 * H), int(0.62 * W):int(0.69 * W)] *= 1.3      # corrupted patch
    return (raw * (1 + rng.normal(0, 0.003, raw.shape))).astype(np.float32)


def test_refinement_fixes_corrupted_patch_misaligned_edge_and_hole():
    K, poses, views, refs = _views(160, 120, 6)
    color, gt = views[0]
    raw = _corrupt(gt)
    out = refine_depth(color, raw, K, poses[0], refs)
    err_raw, err_ref = np.abs(raw - gt), np.abs(out.depth_m - gt)
    both = (raw > 0) & (out.depth_m > 0)
    # Mean absolute error on pixels valid before and after: the misaligned edge band (3 px x 2
    # edges, 0.6 m jumps) and the 30 % patch dominate the raw error.
    assert err_ref[both].mean() < 0.35 * err_raw[both].mean()
    # Gross errors (> 5 cm) mostly vanish (measured: 421 -> 115 pixels): edge band and patch fixed.
    assert (err_ref[both] > 0.05).sum() < 0.35 * (err_raw[both] > 0.05).sum()
    # The hole (flat textured background) is filled with the right depth.
    hole = raw == 0
    assert out.filled[hole].mean() > 0.95
    assert np.median(err_ref[hole & out.filled]) < 0.01
    assert out.depth_m.dtype == np.float32 and out.depth_m.shape == gt.shape


def test_clean_depth_stays_clean():
    K, poses, views, refs = _views(96, 72, 4)
    color, gt = views[0]
    out = refine_depth(color, gt, K, poses[0], refs)
    ok = out.depth_m > 0
    assert ok.mean() > 0.999
    # Only pixels on the depth edge may flip between fore- and background (ties).
    assert (np.abs(out.depth_m - gt)[ok] > 1e-3).mean() < 0.02


def test_unsupported_pixels_stay_invalid():
    K, poses, views, refs = _views(64, 48, 3)
    color, gt = views[0]
    raw = np.zeros_like(gt)
    out = refine_depth(color, raw, K, poses[0], refs)
    assert not out.depth_m.any()  # nothing to propagate from: no depth is invented


def test_numba_matches_reference_on_tiny_input():
    K, poses, views, refs = _views(28, 20, 4, baseline_m=0.05)
    color, gt = views[0]
    raw = _corrupt(gt, seed=1)
    cfg = RefineConfig(median_radius=2)
    fast = refine_depth(color, raw, K, poses[0], refs, cfg)
    slow = refine_depth(color, raw, K, poses[0], refs, RefineConfig(median_radius=2, backend="reference"))
    # Same order of operations; exp() rounding may flip a near-tie of the weighted median on at
    # most a couple of pixels.
    same = np.isclose(fast.depth_m, slow.depth_m, rtol=0, atol=1e-5)
    assert same.mean() >= 0.99, f"{(~same).sum()} pixels differ"
    finite = np.isfinite(fast.cost) & np.isfinite(slow.cost)
    assert np.array_equal(np.isfinite(fast.cost), np.isfinite(slow.cost))
    assert np.allclose(fast.cost[finite], slow.cost[finite], atol=1e-5)


def test_select_reference_views_nearest_within_angle():
    def rot_y(deg: float) -> np.ndarray:
        a = np.radians(deg)
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    # Target 0 at the origin looking along +z; candidates on the x axis at known distances.
    x_m = [0.0, 0.30, 0.10, 0.50, 0.05, 0.20, 0.15, 0.40, -0.25]
    T = np.stack([make_pose(np.eye(3), [x, 0.0, 0.0]) for x in x_m])
    T[4, :3, :3] = np.diag([1.0, -1.0, -1.0])  # 0.05 m, looks backwards: never a reference
    T[5, :3, :3] = rot_y(70.0)  # 0.20 m, 70 deg off the target's axis: beyond 60 deg
    T[6, :3, :3] = rot_y(50.0)  # 0.15 m, 50 deg: allowed
    refs = select_reference_views(T, 0, range(9), num_refs=4, max_angle_deg=60)
    # Eligible by distance: 2 (0.10), 6 (0.15), 8 (0.25), 1 (0.30), 7 (0.40), 3 (0.50).
    assert refs == [2, 6, 8, 1]
    assert select_reference_views(T, 0, [3, 7, 1], num_refs=2) == [1, 7]
    assert select_reference_views(T, 0, range(9), num_refs=10, max_angle_deg=45) == [2, 8, 1, 7, 3]
    assert select_reference_views(T, 0, [0, 4]) == []


def test_bad_inputs_raise_clear_errors():
    K, poses, views, refs = _views(32, 24, 2)
    color, gt = views[0]
    with pytest.raises(ValueError, match="color must be uint8"):
        refine_depth(color.astype(np.float32), gt, K, poses[0], refs)
    with pytest.raises(ValueError, match="depth must be"):
        refine_depth(color, gt[:-1], K, poses[0], refs)
    with pytest.raises(ValueError, match="patch_size"):
        RefineConfig(patch_size=4)


# ---- blurred references are down-weighted (issue 12, item 4) -------------------------------------

def test_blurred_reference_gets_a_lower_weight():
    import cv2

    from presim.depth.refine import reference_weights

    _, _, views, _ = _views(160, 120, 4)
    colors = [c for c, _ in views[1:]]
    colors[1] = cv2.GaussianBlur(colors[1], (0, 0), 1.5)
    w = reference_weights(colors, gamma=2.0)
    assert max(w) == 1.0 and int(np.argmin(w)) == 1
    assert w[1] < min(w[0], w[2]) - 0.1  # blur sigma 1.5 px: score ~8 % lower, weight (ratio)^2
    assert reference_weights(colors, gamma=0.0) == [1.0, 1.0, 1.0]  # gamma 0 = the thesis' plain mean


def test_zero_weight_reference_is_ignored_and_weights_match_reference_backend():
    import dataclasses

    K, poses, views, refs = _views(28, 20, 4, baseline_m=0.05)
    color, gt = views[0]
    raw = _corrupt(gt, seed=1)
    cfg = RefineConfig(median_radius=2)
    # A reference whose colours are garbage, with weight 0, changes nothing at all.
    junk = dataclasses.replace(refs[0], color=np.random.default_rng(0).integers(0, 256, refs[0].color.shape, np.uint8),
                               weight=0.0)
    a = refine_depth(color, raw, K, poses[0], refs, cfg)
    b = refine_depth(color, raw, K, poses[0], [junk] + list(refs), cfg)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    np.testing.assert_array_equal(a.cost, b.cost)
    # Non-uniform weights: numba and the reference agree (same weighted mean).
    wrefs = [dataclasses.replace(r, weight=w) for r, w in zip(refs, (1.0, 0.3, 0.6))]
    fast = refine_depth(color, raw, K, poses[0], wrefs, cfg)
    slow = refine_depth(color, raw, K, poses[0], wrefs, dataclasses.replace(cfg, backend="reference"))
    finite = np.isfinite(fast.cost) & np.isfinite(slow.cost)
    assert np.array_equal(np.isfinite(fast.cost), np.isfinite(slow.cost))
    assert np.allclose(fast.cost[finite], slow.cost[finite], atol=1e-5)
    assert np.isclose(fast.depth_m, slow.depth_m, rtol=0, atol=1e-5).mean() >= 0.99
    # Weights do change the costs where references disagree.
    assert not np.allclose(fast.cost[finite], a.cost[finite])


def test_sharp_refs_off_keeps_cache_keys():
    from presim.depth.scene_refine import config_key

    assert config_key(RefineConfig()) == config_key(RefineConfig(sharp_refs_gamma=3.0))
    assert "sharp_refs" not in config_key(RefineConfig())
    assert config_key(RefineConfig(sharp_refs=True)) != config_key(RefineConfig())
