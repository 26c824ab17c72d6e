"""KinectFusion / 7-Scenes importer: real data, written files, bad input, lossless save/load,
and the reprojection check of the real capture's poses."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import synth_frames, write_kinfu  # noqa: E402

from presim.capture.importers import detect_format, import_capture  # noqa: E402
from presim.capture.importers import kinfu  # noqa: E402
from presim.capture.reprojection import reprojection_mae  # noqa: E402
from presim.capture.scene import SceneError  # noqa: E402
from presim.capture.store import load_scene, save_scene  # noqa: E402
from presim.io_utils import write_png  # noqa: E402


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def test_real_kinfu50(shared_data):
    src = shared_data("apc_cardboard_bin_kinfu50")
    assert detect_format(src) == "kinfu"
    s = kinfu.read(src)
    assert len(s) == 50 and s.frame_ids[0] == "frame-000015" and s.frame_ids[-1] == "frame-000113"
    assert s.width == 640 and s.height == 480
    assert s.intrinsics[0].fx == pytest.approx(615.1951904296875)
    np.testing.assert_array_equal(s.T_world_cam[0], np.eye(4))  # first frame = identity (README)
    assert s.stamps_s[1] - s.stamps_s[0] == pytest.approx(2 / 30)  # stored every other frame
    f = s.frame(10)
    assert f.color.dtype == np.uint8 and f.depth_m.dtype == np.float32
    v = f.depth_m[f.depth_m > 0]
    assert 0.25 < (f.depth_m > 0).mean() < 0.45  # README: ~34 % valid
    assert 0.05 < v.min() and v.max() < 2.0  # millimetres decoded to metres
    assert 0.4 < s.trajectory_length_m() < 0.6  # README: ~0.50 m


def test_real_kinfu50_reprojection_far_below_no_motion(shared_data):
    """README pairs; poses are camera-to-world: the warp error must be far below the identity one
    (README: 7.0 vs 25.0; this implementation measures ~7.5 vs ~24.9)."""
    s = kinfu.read(shared_data("apc_cardboard_bin_kinfu50"))
    idx = {fid: i for i, fid in enumerate(s.frame_ids)}
    pairs = [(31, 29), (31, 35), (61, 59), (61, 65), (91, 89), (101, 105)]
    with_pose, no_motion, cov = [], [], []
    for t, so in pairs:
        ti, si = idx[f"frame-{t:06d}"], idx[f"frame-{so:06d}"]
        m, c = reprojection_mae(s, ti, si)
        with_pose.append(m)
        cov.append(c)
        no_motion.append(reprojection_mae(s, ti, si, use_poses=False)[0])
    mae, base = float(np.mean(with_pose)), float(np.mean(no_motion))
    assert mae < 10.0 and base > 20.0 and mae < 0.45 * base, (mae, base)
    assert 0.25 < np.mean(cov) < 0.45
    # Inverting the poses (the world-to-camera mistake) must be clearly worse than the right reading.
    from dataclasses import replace

    from presim.geometry import invert

    wrong = replace(s, T_world_cam=invert(s.T_world_cam))
    ti, si = idx["frame-000061"], idx["frame-000065"]
    assert reprojection_mae(wrong, ti, si)[0] > reprojection_mae(s, ti, si)[0] + 5


def test_synthetic_roundtrip_and_lossless(tmp_path):
    f = synth_frames(n=3)
    src = write_kinfu(tmp_path / "cap", f)
    s = import_capture(src, align_floor=False)
    assert s.meta.source_format == "kinfu"
    assert s.frame_ids == ["frame-000000", "frame-000001", "frame-000002"]
    np.testing.assert_allclose(s.stamps_s, [100.0, 100.1, 100.2])  # from timestamps.txt
    np.testing.assert_allclose(s.T_world_cam, f.T_world_cam, atol=1e-12)
    assert s.intrinsics[0] == f.K
    for i in range(3):
        c, d = s.frames.load(i)
        np.testing.assert_array_equal(c, f.color[i])
        np.testing.assert_array_equal(d, f.depth_m[i])
    dst = save_scene(s, tmp_path / "scene")
    back = load_scene(dst)
    assert back.frame_ids == s.frame_ids and back.intrinsics == s.intrinsics
    np.testing.assert_array_equal(back.T_world_cam, s.T_world_cam)
    np.testing.assert_array_equal(back.stamps_s, s.stamps_s)
    np.testing.assert_array_equal(back.gravity_world, s.gravity_world)
    assert back.meta.notes == s.meta.notes
    for i in range(3):
        np.testing.assert_array_equal(back.frame(i).color, s.frame(i).color)
        np.testing.assert_array_equal(back.frame(i).depth_m, s.frame(i).depth_m)


def test_jpg_intrinsics_K_default_stamps_and_every(tmp_path):
    f = synth_frames(n=5)
    src = write_kinfu(tmp_path / "cap", f, intrinsics_name="intrinsics.K.txt", timestamps=False, jpg=True)
    s = import_capture(src, every=2, max_frames=2, align_floor=False)
    assert s.frame_ids == ["frame-000000", "frame-000002"]
    np.testing.assert_allclose(s.stamps_s, [0.0, 2 / 30])
    assert s.frame(1).color.shape == (30, 40, 3)


def test_invalid_codes_become_zero(tmp_path):
    f = synth_frames(n=1)
    f.depth_mm[0, 0, :5] = 65535
    src = write_kinfu(tmp_path / "cap", f)
    d = kinfu.read(src).frame(0).depth_m
    assert np.all(d[0, :5] == 0)


@pytest.mark.parametrize("problem", ["missing_depth", "corrupt_color", "nan_pose", "scaled_pose",
                                     "size_mismatch", "no_intrinsics", "empty_depth", "bad_stamp"])
def test_bad_input_names_file(tmp_path, problem):
    f = synth_frames(n=2)
    src = write_kinfu(tmp_path / "cap", f)
    culprit = None
    if problem == "missing_depth":
        culprit = src / "frame-000001.depth.png"
        culprit.unlink()
    elif problem == "corrupt_color":
        culprit = src / "frame-000001.color.png"
        culprit.write_bytes(b"not a png")
    elif problem == "nan_pose":
        culprit = src / "frame-000001.pose.txt"
        T = f.T_world_cam[1].copy()
        T[0, 3] = np.nan
        np.savetxt(culprit, T)
    elif problem == "scaled_pose":
        culprit = src / "frame-000000.pose.txt"
        T = f.T_world_cam[0].copy()
        T[:3, :3] *= 1.1
        np.savetxt(culprit, T)
    elif problem == "size_mismatch":
        culprit = src / "frame-000001.depth.png"
        write_png(culprit, np.ones((10, 12), np.uint16))
    elif problem == "no_intrinsics":
        (src / "camera-intrinsics.txt").unlink()
        culprit = "camera-intrinsics.txt"
    elif problem == "empty_depth":
        culprit = src / "frame-000001.depth.png"
        write_png(culprit, np.zeros((30, 40), np.uint16))
    elif problem == "bad_stamp":
        culprit = src / "timestamps.txt"
        culprit.write_text("frame-000000 abc\n")
    with pytest.raises((SceneError, FileNotFoundError)) as ei:
        s = import_capture(src, align_floor=False)
        save_scene(s, tmp_path / "out")
    assert str(culprit) in str(ei.value), str(ei.value)
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_frames_are_read_lazily(tmp_path):
    """Import reads no pixels: a color file removed after import only fails when that frame is read,
    and the error names it."""
    src = write_kinfu(tmp_path / "cap", synth_frames(n=3))
    s = kinfu.read(src)
    (src / "frame-000002.color.png").unlink()
    s.frame(0)
    with pytest.raises(SceneError, match="frame-000002.color.png: file not found"):
        s.frame(2)


def test_recording_folder_uses_its_capture_subfolder(tmp_path):
    """`presim drive --record DIR` writes DIR/recording.mcap and DIR/capture/ (kinfu layout)."""
    write_kinfu(tmp_path / "rec" / "capture", synth_frames(n=2))
    (tmp_path / "rec" / "recording.mcap").write_bytes(b"")
    s = import_capture(tmp_path / "rec", align_floor=False)
    assert len(s) == 2 and s.meta.source.endswith("capture")
