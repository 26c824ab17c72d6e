"""Depth alignment (thesis §5.3.4.1, Alg. 2) and fusion (§5.3.4.2) with answers known on paper."""

from __future__ import annotations

import numpy as np
import pytest

from presim.depth.align import AlignConfig, align_depth, fit_scale_ransac
from presim.depth.fuse import SOURCE_ESTIMATE, SOURCE_SENSOR, FuseConfig, fuse_depth, sensor_reliability
from presim.geometry import Intrinsics


def _K(w: int, h: int) -> Intrinsics:
    return Intrinsics(fx=100.0, fy=100.0, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)


def _step(w: int, h: int, edge_u: int, near: float = 1.0, far: float = 2.0) -> np.ndarray:
    d = np.full((h, w), far, np.float32)
    d[:, :edge_u] = near
    return d


@pytest.mark.parametrize("k", [1, 3, 5])
@pytest.mark.parametrize("sign", [1, -1])
def test_step_edge_shifted_by_k_pixels_is_aligned_back(k, sign):
    w, h = 40, 24
    est = _step(w, h, 20)
    cap = _step(w, h, 20 + sign * k)          # sensor foreground bleeds k px right (or falls short)
    out = align_depth(cap, est, _K(w, h))
    assert out.scale == pytest.approx(1.0)
    np.testing.assert_array_equal(out.depth_m, est)
    # Only the band of k columns moved, by k pixels along x; everything else keeps offset 0.
    moved = np.any(out.offsets != 0, axis=2)
    assert moved.sum() == k * h
    assert set(np.abs(out.offsets[..., 0][moved]).tolist()) <= set(range(1, k + 1))
    assert np.all(out.offsets[..., 1] == 0)
    assert out.cost_sums[-1] < out.cost_sums[0]


def test_shift_in_both_axes_and_noise_free_flat_regions_keep_zero_offsets():
    w, h = 36, 30
    est = np.full((h, w), 2.0, np.float32)
    est[10:20, 12:24] = 1.2                      # a box in front
    cap = np.roll(np.roll(est, 2, axis=0), -2, axis=1)
    out = align_depth(cap, est, _K(w, h))
    np.testing.assert_array_equal(out.depth_m, est)
    far = np.ones((h, w), bool)
    far[6:24, 8:28] = False                      # away from the box and its shifted copy
    assert np.all(out.offsets[far] == 0)


def test_scale_is_fitted_by_ransac_with_outliers():
    rng = np.random.default_rng(1)
    est = rng.uniform(1.0, 3.0, (50, 60)).astype(np.float32)
    cap = (1.25 * est).astype(np.float32)
    cap[:10] = rng.uniform(0.5, 5.0, (10, 60))   # 20 % outliers
    assert fit_scale_ransac(cap, est) == pytest.approx(1.25, rel=1e-6)
    assert fit_scale_ransac(cap, est, AlignConfig(seed=3)) == pytest.approx(1.25, rel=1e-6)


def test_reference_and_numba_agree_on_a_noisy_scene():
    rng = np.random.default_rng(0)
    w, h = 28, 22
    K = _K(w, h)
    yy, xx = np.mgrid[0:h, 0:w]
    est = (2.0 + 0.02 * xx + 0.01 * yy).astype(np.float32)          # slanted plane
    est[6:15, 8:18] = 1.1                                           # box
    est[0:3, 20:26] = 0                                             # estimate hole
    cap = np.roll(est, 3, axis=1) * (1 + rng.normal(0, 0.01, est.shape))
    cap[:, :4] = 0                                                  # dead band
    cap[17:20, 5:9] = 0
    cap = cap.astype(np.float32)
    for cfg in (AlignConfig(), AlignConfig(max_offset_px=2, offset_penalty=0.0, max_normal_angle_deg=10.0)):
        a = align_depth(cap, est, K, cfg)
        b = align_depth(cap, est, K, AlignConfig(**{**cfg.__dict__, "backend": "reference"}))
        np.testing.assert_array_equal(a.offsets, b.offsets)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        np.testing.assert_allclose(a.cost, b.cost, atol=1e-6)
        np.testing.assert_allclose(a.cost_sums, b.cost_sums, rtol=1e-9)
        assert len(a.cost_sums) >= 2


def test_dead_band_is_filled_with_the_estimate():
    w, h = 40, 20
    est = _step(w, h, 25, 1.5, 2.5)
    cap = est.copy()
    cap[:, :6] = 0                                                  # stereo dead band (left)
    cap[8:12, 30:34] = 0                                            # dark / reflective patch
    al = align_depth(cap, est, _K(w, h))
    fu = fuse_depth(al.depth_m, est, scale=al.scale)
    np.testing.assert_array_equal(fu.depth_m, est)
    assert np.all(fu.source[:, :6] == SOURCE_ESTIMATE)
    assert np.all(fu.source[8:12, 30:34] == SOURCE_ESTIMATE)
    assert np.all(fu.source[:, 8:20] == SOURCE_SENSOR)


def test_constant_offset_plane_keeps_sensor_values():
    est = np.full((20, 30), 2.0, np.float32)
    cap = np.full((20, 30), 2.04, np.float32)                       # 2 % off, within agree_rel
    fu = fuse_depth(align_depth(cap, est, _K(30, 20), AlignConfig(fit_scale=False)).depth_m, est)
    np.testing.assert_array_equal(fu.depth_m, cap)
    assert np.all(fu.source == SOURCE_SENSOR)
    # agree_value="estimate" takes the estimate where both agree.
    np.testing.assert_array_equal(fuse_depth(cap, est, FuseConfig(agree_value="estimate")).depth_m, est)
    with pytest.raises(ValueError, match="agree_value"):
        FuseConfig(agree_value="mean")


def test_disagreement_at_an_edge_takes_the_estimate_and_away_from_edges_the_sensor():
    est = _step(30, 20, 15, 1.0, 2.0)
    a = est.copy()
    a[:, 15] = 1.0                       # residual bleed right at the edge
    a[5, 25] = 2.5                       # disagreement far from any edge
    fu = fuse_depth(a, est)
    np.testing.assert_array_equal(fu.depth_m[:, 15], est[:, 15])
    assert fu.depth_m[5, 25] == pytest.approx(2.5)
    # Beyond the sensor's range the estimate wins a disagreement.
    fu2 = fuse_depth(a, est, FuseConfig(max_range_m=2.2))
    assert fu2.depth_m[5, 25] == pytest.approx(2.0)


def test_sensor_reliability_eq_5_7():
    r = sensor_reliability(np.array([0.1, 1.0, 3.0, 5.0]), 0.5, 4.0)
    np.testing.assert_allclose(r, [0.0, (16 - 1) / (16 - 0.25), (16 - 9) / (16 - 0.25), 0.0], rtol=1e-6)


# ---- scene level: presim fuse, info, renderer, eval-views --------------------------------------------

def _saved_two_plane_scene(tmp_path, with_refined: bool):
    from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
    from presim.capture.store import save_scene
    from presim.testing.two_planes import render_two_planes, two_plane_poses

    K = Intrinsics.from_fov(64, 48, 60.0)
    poses = two_plane_poses(4, 0.05)
    views = [render_two_planes(T, K) for T in poses]
    truth = np.stack([d for _, d in views])
    raw = np.roll(truth, 2, axis=2)                  # sensor depth 2 px off the colour edges
    raw[:, :, :8] = 0                                # and a dead band on the left
    scene = Scene([f"f{i}" for i in range(4)], np.arange(4.0), poses, [K] * 4,
                  ArrayFrameSource(np.stack([c for c, _ in views]), raw), SceneMeta("two planes", "synthetic"),
                  depth_refined=truth if with_refined else None)
    return save_scene(scene, tmp_path / "s"), truth, raw


def test_cli_fuse_writes_depth_fused_and_info_shows_it(tmp_path, capsys, monkeypatch):
    import json

    from presim.capture.store import load_scene
    from presim.cli import main
    from presim.synthesis.renderer import RenderConfig, Renderer

    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    path, truth, raw = _saved_two_plane_scene(tmp_path, with_refined=True)
    assert main(["info", str(path)]) == 0
    assert "fused depth no" in capsys.readouterr().out
    assert main(["fuse", str(path)]) == 0
    assert "wrote" in capsys.readouterr().out
    fused = np.load(path / "depth_fused.npy")
    # Edges moved back onto the colour edges and the dead band filled: the fused depth is the truth.
    np.testing.assert_allclose(fused, truth, rtol=1e-6)
    np.testing.assert_array_equal(np.load(path / "depth.npy"), raw)           # never overwritten
    np.testing.assert_array_equal(np.load(path / "depth_refined.npy"), truth)
    assert not (path / "depth_fused.npy.partial").exists()
    assert json.loads((path / "scene.json").read_text())["has_fused_depth"] is True
    assert main(["info", str(path)]) == 0
    assert "fused depth yes" in capsys.readouterr().out
    assert main(["fuse", str(path)]) == 1                                     # exists: needs --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["fuse", str(path), "--overwrite"]) == 0
    scene = load_scene(path)
    assert scene.has_fused_depth and scene.subset([2, 1]).depth_fused[0].shape == (48, 64)
    r = Renderer(scene, RenderConfig(use_fused_depth=True))
    np.testing.assert_array_equal(r._load_frame(1)[1], fused[1])
    assert main(["render", str(path), "--frame", "1", "--fused-depth", "--out", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    assert main(["render", str(path), "--frame", "1", "--fused-depth", "--raw-depth", "--out", str(tmp_path / "x")]) == 1
    assert "exclude each other" in capsys.readouterr().err


def test_cli_fuse_needs_refined_depth(tmp_path, capsys):
    from presim.cli import main

    path, _, _ = _saved_two_plane_scene(tmp_path, with_refined=False)
    assert main(["fuse", str(path)]) == 1
    err = capsys.readouterr().err
    assert "presim refine" in err and "Traceback" not in err
    assert not (path / "depth_fused.npy").exists()


def test_eval_views_fused_method_runs(tmp_path, monkeypatch):
    from presim.capture.store import load_scene
    from presim.depth.refine import RefineConfig
    from presim.evaluation.eval_views import EvalConfig, eval_views

    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    path, _, _ = _saved_two_plane_scene(tmp_path, with_refined=False)
    res = eval_views(load_scene(path), EvalConfig(stride=1, target_every=2, methods=("thesis", "fused"),
                                                  refine=RefineConfig(median_radius=2)))
    assert set(res.methods) == {"thesis", "fused"}
    assert np.isfinite(res.methods["fused"]["psnr_db"])
