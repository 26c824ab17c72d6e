"""APC shelf and YCB-Video importers on the real data in ../shared/data, and bad-input cases."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from presim.capture.importers import apc_shelf, detect_format, import_capture, ycbv  # noqa: E402
from presim.capture.reprojection import reprojection_mae  # noqa: E402
from presim.capture.scene import SceneError  # noqa: E402
from presim.capture.store import load_scene, save_scene  # noqa: E402
from presim.geometry import project, transform_points, invert  # noqa: E402


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def test_apc_shelf_real(shared_data):
    src = shared_data("apc_shelf_scene0000")
    assert detect_format(src) == "apc_shelf"
    s = apc_shelf.read(src)
    assert len(s) == 15 and s.frame_ids[0] == "frame-000000"
    assert s.intrinsics[0].fx == pytest.approx(615.195190)
    d = s.frame(2).depth_m
    v = d[d > 0]
    assert 0.2 < (d > 0).mean() < 0.33  # README: ~26 % valid
    assert 0.05 < v.min() and v.max() < 1.6 and 0.4 < np.median(v) < 0.7  # README: median 0.55 m
    # README reprojection check: pairs (2,1) (2,3) (7,6) (7,8) (12,11) (12,13): 21.6 vs 46.2 identity
    pairs = [(2, 1), (2, 3), (7, 6), (7, 8), (12, 11), (12, 13)]
    mae = np.mean([reprojection_mae(s, a, b)[0] for a, b in pairs])
    base = np.mean([reprojection_mae(s, a, b, use_poses=False)[0] for a, b in pairs])
    assert mae < 25 and base > 40, (mae, base)


def test_apc_shelf_wrong_decode_would_fail(shared_data):
    """The bit rotation matters: a plain /10000 read gives depths of several metres."""
    from presim.io_utils import read_image

    src = shared_data("apc_shelf_scene0000")
    raw = read_image(src / "frame-000002.depth.png", kind="depth")
    naive = raw[raw > 0] / 10000.0
    good = apc_shelf.decode_apc_depth(raw, src)
    assert np.median(naive) > 2 * np.median(good[good > 0])


def test_apc_shelf_lossless_and_corrupt_info(shared_data, tmp_path):
    src = shared_data("apc_shelf_scene0000")
    s = import_capture(src, max_frames=3)
    back = load_scene(save_scene(s, tmp_path / "scene"))
    np.testing.assert_array_equal(back.T_world_cam, s.T_world_cam)
    np.testing.assert_array_equal(back.frame(1).depth_m, s.frame(1).depth_m)
    np.testing.assert_array_equal(back.points.xyz, s.points.xyz)
    # a corrupt pose section names cam.info.txt
    cap = tmp_path / "cap"
    cap.mkdir()
    for p in src.glob("frame-00000[01]*"):
        shutil.copy(p, cap / p.name)
    text = (src / "cam.info.txt").read_text()
    (cap / "cam.info.txt").write_text(text.replace("4.35946526e-01", "nan", 1))
    with pytest.raises(SceneError, match=r"cam.info.txt: pose of frame-000000: contains non-finite"):
        import_capture(cap, align_floor=False)


def test_ycbv_real(shared_data):
    src = shared_data("ycbv_2frames")
    assert detect_format(src) == "ycbv"
    s = ycbv.read(src)
    assert s.frame_ids == ["000001", "000002"]
    assert s.intrinsics[0].fx == pytest.approx(1066.778)
    names = [o.name for o in s.objects]
    assert names == ["002_master_chef_can", "004_sugar_box", "009_gelatin_box", "010_potted_meat_can",
                     "019_pitcher_base", "025_mug", "061_foam_brick"]
    d = s.frame(0).depth_m
    assert 0.4 < d[d > 0].min() and d.max() < 3.0  # README: 0.50-2.58 m
    # README check: model points projected with the GT poses land on the depth surface (median |dz| few mm)
    for k, fr in ((0, "009_gelatin_box"), (1, "004_sugar_box")):
        obj = next(o for o in s.objects if o.name == fr)
        pts = np.loadtxt(obj.model_path)
        T_cam_obj = invert(s.T_world_cam[k]) @ obj.T_world_obj
        p_cam = transform_points(T_cam_obj, pts)
        uv, z = project(s.intrinsics[k], p_cam)
        u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        dk = s.frame(k).depth_m
        ok = (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
        dz = dk[v[ok], u[ok]] - z[ok]
        front = (dk[v[ok], u[ok]] > 0) & (np.abs(dz) < 0.05)
        assert front.mean() > 0.3 and np.median(np.abs(dz[front])) < 0.01


def test_ycbv_save_copies_point_models(shared_data, tmp_path):
    s = import_capture(shared_data("ycbv_2frames"))
    back = load_scene(save_scene(s, tmp_path / "scene"))
    assert len(back.objects) == 7
    m = back.objects[0].model_path
    assert m.startswith("objects/") and m.endswith(".xyz") and (back.path / m).is_file()
    np.testing.assert_array_equal(back.objects[3].T_world_obj, s.objects[3].T_world_obj)


def test_ycbv_bad_meta(shared_data, tmp_path):
    src = shared_data("ycbv_2frames")
    cap = tmp_path / "y"
    shutil.copytree(src / "models", cap / "models")
    (cap / "data").mkdir()
    for p in (src / "data").glob("000001-*"):
        shutil.copy(p, cap / "data" / p.name)
    (cap / "data" / "000001-meta.mat").write_bytes(b"garbage")
    with pytest.raises(SceneError, match="000001-meta.mat: unreadable or corrupt"):
        import_capture(cap, align_floor=False)
