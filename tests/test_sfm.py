"""Initial poses of a capture without poses (presim/align/sfm.py): pycolmap incremental SfM,
metric scale from the depth, loop pairs from the capture's own bag of words, and the import around it
(missing pycolmap, too few registered frames: clear error, nothing written)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from align_synthetic import synthetic_scene  # noqa: E402

from presim.align.pipeline import fit_rigid_to, pose_change  # noqa: E402
from presim.align.sfm import (  # noqa: E402
    SfmConfig, SfmError, SfmUnavailable, estimate_poses_sfm, metric_scale, retrieval_pairs)


def _errors(T_true, T_est):
    S = fit_rigid_to(T_true, T_est)
    return pose_change(T_true, S @ T_est)


def test_metric_scale_is_the_robust_median_ratio():
    """Sensor depth = 2.5 x SfM depth on 90 keypoints, 10 gross outliers and 5 invalid: scale 2.5,
    spread (MAD / median) 0."""
    rng = np.random.default_rng(0)
    sfm = rng.uniform(0.5, 2.0, 105)
    sensor = 2.5 * sfm
    sensor[:10] = rng.uniform(10, 20, 10)
    sensor[10:15] = 0
    scale, spread, count = metric_scale(sfm, sensor)
    assert scale == pytest.approx(2.5) and spread == pytest.approx(0.0, abs=1e-12) and count == 100
    with pytest.raises(SfmError, match="only 3 SfM points have sensor depth"):
        metric_scale(sfm[:3], sensor[20:23])


def test_retrieval_pairs_find_the_revisit():
    """20 frames, each with its own random descriptors, except that frame 17 sees what frame 2 saw
    (a loop): with a sequential window of 3 and one loop neighbour, (2, 17) is a pair; no pair lies
    inside the window."""
    rng = np.random.default_rng(1)
    desc = [rng.integers(0, 256, (150, 128)).astype(np.uint8) for _ in range(20)]
    desc[17] = desc[2][rng.permutation(150)]
    pairs = retrieval_pairs(desc, SfmConfig(sequential_overlap=3, loop_neighbours=1, vocabulary_words=64))
    assert (2, 17) in pairs
    assert all(b - a > 3 for a, b in pairs)
    assert pairs == retrieval_pairs(desc, SfmConfig(sequential_overlap=3, loop_neighbours=1, vocabulary_words=64))
    assert retrieval_pairs(desc, SfmConfig(loop_neighbours=0)) == []


def test_missing_pycolmap_gives_the_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap -> ImportError
    scene, _ = synthetic_scene(2, width=64, height=48)
    with pytest.raises(SfmUnavailable, match=r"needs pycolmap 4\.x.*presim\[sfm\]"):
        estimate_poses_sfm(scene)


@pytest.mark.slow
def test_sfm_recovers_synthetic_poses_and_is_deterministic():
    """8 frames of the two-plane capture (exact depth): SfM poses, scaled by the depth, match the true
    ones after a rigid fit within 1 mm / 0.05 deg (measured 0.31 mm / 0.008 deg); the scale spread is
    under 1 %; the same seed gives the same poses bit for bit."""
    scene, T = synthetic_scene(8)
    cfg = SfmConfig()
    r = estimate_poses_sfm(scene, cfg)
    assert r.registered_idxs == list(range(8))
    assert r.stats["scale_spread_mad_rel"] < 0.01
    np.testing.assert_allclose(r.T_world_cam[0], np.eye(4), atol=1e-12)  # world = first registered camera
    dt, dr = _errors(T, r.T_world_cam)
    assert dt.max() < 1e-3 and dr.max() < 0.05, (dt.max(), dr.max())
    again = estimate_poses_sfm(scene, cfg)
    assert np.array_equal(again.T_world_cam, r.T_world_cam)


@pytest.mark.slow
def test_import_without_poses_too_few_registered_writes_nothing(tmp_path):
    """A KinectFusion folder without poses whose last 6 of 8 frames are blank (no features): SfM
    registers at most 2 (here none: the two textured frames are 4 cm apart, too little parallax for
    an initial pair), below 80 %: `presim import` exits with one line naming the frames and leaves no
    scene."""
    from test_capture_writers import SynthFrames, write_kinfu

    scene, T = synthetic_scene(8)
    color = np.array(scene.frames.color)
    color[2:] = 128
    depth_mm = np.round(np.array(scene.frames.depth_m) * 1000).astype(np.uint16)
    src = write_kinfu(tmp_path / "kf", SynthFrames(scene.intrinsics[0], color, depth_mm, T))
    for p in src.glob("frame-*.pose.txt"):
        p.unlink()
    dst = tmp_path / "scene"
    r = subprocess.run([sys.executable, "-m", "presim", "import", str(src), str(dst), "--no-floor"],
                       capture_output=True, text=True)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert "frames could be registered by SfM (need 80%)" in last and "frame-000002" in last, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    assert not dst.exists()


def test_kinfu_folder_without_poses_is_detected_with_either_intrinsics_file(tmp_path):
    """APC-style folders name their intrinsics `intrinsics.K.txt`; without pose files they are still a
    kinfu capture (poses estimated at import), as `kinfu.read` accepts that name too."""
    from test_capture_writers import SynthFrames, write_kinfu

    from presim.capture.importers.registry import detect_format

    scene, T = synthetic_scene(2, width=64, height=48)
    depth_mm = np.round(np.array(scene.frames.depth_m) * 1000).astype(np.uint16)
    src = write_kinfu(tmp_path / "kf", SynthFrames(scene.intrinsics[0], np.array(scene.frames.color), depth_mm, T),
                      intrinsics_name="intrinsics.K.txt")
    for p in src.glob("frame-*.pose.txt"):
        p.unlink()
    assert detect_format(src) == "kinfu"
