"""Scene-level refinement: partial file + per-frame markers, resume after an interruption, and the
depth filtering baselines."""

from __future__ import annotations

import numpy as np
import pytest

from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
from presim.capture.store import load_scene, save_scene
from presim.depth.filters import guided_filter_depth, median_filter_depth
from presim.depth.refine import RefineConfig
from presim.depth.scene_refine import refine_frames_to_file, refine_scene
from presim.testing.two_planes import render_two_planes, two_plane_poses
from presim.geometry import Intrinsics


def tiny_scene(n: int = 5, width: int = 48, height: int = 36) -> Scene:
    K = Intrinsics.from_fov(width, height, 60.0)
    poses = two_plane_poses(n, 0.05)
    views = [render_two_planes(T, K) for T in poses]
    color = np.stack([c for c, _ in views])
    depth = np.stack([d for _, d in views])
    depth[:, 10:14, 5:9] = 0  # a hole to fill
    return Scene([f"frame-{i:06d}" for i in range(n)], np.arange(n, dtype=float), poses, [K] * n,
                 ArrayFrameSource(color, depth), SceneMeta("two planes", "synthetic"))


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


CFG = RefineConfig(median_radius=2)


def test_refine_resumes_after_interruption(tmp_path):
    scene = load_scene(save_scene(tiny_scene(), tmp_path / "s"))
    raw_before = np.load(tmp_path / "s" / "depth.npy").copy()
    out = tmp_path / "s" / "depth_refined.npy"
    # "Interrupt" after 2 frames: the partial file and 2 markers remain, no final file.
    assert refine_scene(scene, config=CFG, max_frames=2) is None
    assert not out.exists()
    assert (tmp_path / "s" / "depth_refined.npy.partial").is_file()
    markers = sorted(p.name for p in (tmp_path / "s" / "depth_refined.npy.done").iterdir())
    assert markers == ["000000", "000001", "fingerprint.json"]
    # Poison a finished row: a resumed run must keep it (not recompute), proving it resumed.
    part = np.load(tmp_path / "s" / "depth_refined.npy.partial", mmap_mode="r+")
    part[0, 0, 0] = 123.0
    part.flush()
    del part
    assert refine_scene(scene, config=CFG) == out
    assert not (tmp_path / "s" / "depth_refined.npy.partial").exists()
    assert not (tmp_path / "s" / "depth_refined.npy.done").exists()
    resumed = np.load(out)
    assert resumed[0, 0, 0] == 123.0
    # Rows 1.. equal a run from scratch; the raw depth is untouched.
    fresh = refine_frames_to_file(scene, tmp_path / "fresh.npy", config=CFG)
    np.testing.assert_array_equal(np.load(fresh)[1:], resumed[1:])
    np.testing.assert_array_equal(np.load(tmp_path / "s" / "depth.npy"), raw_before)
    assert load_scene(tmp_path / "s").depth_refined is not None
    with pytest.raises(FileExistsError):
        refine_scene(scene, config=CFG)


def test_changed_config_restarts_partial(tmp_path):
    scene = load_scene(save_scene(tiny_scene(3), tmp_path / "s"))
    refine_scene(scene, config=CFG, max_frames=1)
    out = refine_scene(scene, config=RefineConfig(median_radius=1))
    assert out is not None and np.load(out).shape == (3, 36, 48)


@pytest.mark.slow
def test_parallel_workers_match_serial(tmp_path):
    scene = load_scene(save_scene(tiny_scene(4), tmp_path / "s"))
    par = refine_scene(scene, workers=2, config=CFG)
    ser = refine_frames_to_file(scene, tmp_path / "ser.npy", config=CFG)
    np.testing.assert_array_equal(np.load(par), np.load(ser))


def test_cli_refine(tmp_path):
    from presim.cli import main

    save_scene(tiny_scene(3), tmp_path / "s")
    assert main(["refine", str(tmp_path / "s")]) == 0
    assert np.load(tmp_path / "s" / "depth_refined.npy").shape == (3, 36, 48)
    # refine completes the new refined depth; `presim complete` alone refuses to overwrite unless asked
    assert np.load(tmp_path / "s" / "depth_completed.npy").shape == (3, 36, 48)
    assert load_scene(tmp_path / "s").depth_completed is not None
    # ... and fits the renderer's reconstruction filter on it
    assert load_scene(tmp_path / "s").render_filter_sigma_px is not None
    save_scene(tiny_scene(1), tmp_path / "one")
    assert main(["refine", str(tmp_path / "one")]) == 0  # one frame: nothing to fit the filter on
    assert load_scene(tmp_path / "one").render_filter_sigma_px is None
    assert main(["complete", str(tmp_path / "s")]) == 1
    assert main(["complete", str(tmp_path / "s"), "--overwrite"]) == 0
    assert main(["refine", str(tmp_path / "nope")]) == 1


def test_guided_and_median_filters_fill_small_holes_and_keep_planes():
    K = Intrinsics.from_fov(64, 48, 60.0)
    color, gt = render_two_planes(np.eye(4), K)
    raw = gt.copy()
    raw[20:23, 5:8] = 0
    for out in (guided_filter_depth(color, raw), median_filter_depth(raw)):
        assert out.dtype == np.float32 and out.shape == gt.shape
        assert (out[20:23, 5:8] > 0).all()
        far = np.abs(gt - 2.0) < 1e-6
        assert np.median(np.abs(out - gt)[far]) < 1e-3
    with pytest.raises(ValueError, match="ksize"):
        from presim.depth.filters import MedianFilterConfig
        median_filter_depth(raw, MedianFilterConfig(ksize=4))
