"""TUM, COLMAP (text + binary), nerfstudio and BOP importers on files the tests write, and the
cross-format test: the same frames written in different formats import to the same scene."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import (  # noqa: E402
    BOP_T_WORLD_OBJ, synth_frames, tum_stamps, write_bop, write_colmap, write_kinfu,
    write_nerfstudio, write_tum,
)

from presim.capture.importers import detect_format, import_capture  # noqa: E402
from presim.capture.importers import colmap, tum  # noqa: E402
from presim.capture.scene import SceneError  # noqa: E402
from presim.capture.store import load_scene, save_scene  # noqa: E402
from presim.geometry import make_pose, pose_to_tum, quat_xyzw_to_R  # noqa: E402


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def _assert_frames_equal(s, f, depth_atol=0.0):
    np.testing.assert_allclose(s.T_world_cam, f.T_world_cam, atol=1e-6)
    for i in range(len(f)):
        c, d = s.frames.load(i)
        np.testing.assert_array_equal(c, f.color[i])
        np.testing.assert_allclose(d, f.depth_m[i], atol=depth_atol, rtol=0)
        assert s.intrinsics[i].fx == pytest.approx(f.K.fx) and s.intrinsics[i].cx == pytest.approx(f.K.cx)


# ---- TUM --------------------------------------------------------------------------------------
def test_tum(tmp_path):
    f = synth_frames(n=4)
    src = write_tum(tmp_path / "tum", f)
    assert detect_format(src) == "tum"
    s = import_capture(src, align_floor=False)
    np.testing.assert_allclose(s.stamps_s, tum_stamps(4))
    _assert_frames_equal(s, f, depth_atol=1e-6)  # 1/5000 m units hold whole mm exactly


def test_tum_association_and_interpolation():
    pairs = tum.associate(np.array([0.0, 0.033, 0.066, 0.2]), np.array([0.001, 0.03, 0.07, 0.5]), 0.02)
    assert pairs == [(0, 0), (1, 1), (2, 2)]  # 0.2 has no partner within 20 ms
    # one depth stamp, two candidates: the closer rgb wins, one-to-one
    assert tum.associate(np.array([0.0, 0.004]), np.array([0.005]), 0.02) == [(1, 0)]
    R1 = quat_xyzw_to_R(np.array([0, 0, np.sin(0.5), np.cos(0.5)]))  # 1 rad about z
    gt_st = np.array([0.0, 1.0])
    gt_v = np.array([pose_to_tum(np.eye(4)), pose_to_tum(make_pose(R1, [2.0, 0, 0]))])
    T = tum.interpolate_pose(gt_st, gt_v, 0.25, max_gap_s=2.0)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0, 0], atol=1e-12)
    assert np.arctan2(T[1, 0], T[0, 0]) == pytest.approx(0.25)  # slerp: quarter of the angle
    assert tum.interpolate_pose(gt_st, gt_v, 0.25, max_gap_s=0.5) is None  # mocap gap
    assert tum.interpolate_pose(gt_st, gt_v, 1.5, max_gap_s=2.0) is None  # outside the range


def test_tum_drops_frames_outside_ground_truth(tmp_path):
    f = synth_frames(n=4)
    src = write_tum(tmp_path / "tum", f)
    lines = (src / "groundtruth.txt").read_text().splitlines()
    (src / "groundtruth.txt").write_text("\n".join(lines[:1 + 3 * 3]) + "\n")  # gt for 3 frames only
    s = import_capture(src, align_floor=False)
    assert len(s) == 3 and any("1 rgb frames dropped" in n for n in s.meta.notes)


def test_tum_bad_groundtruth(tmp_path):
    src = write_tum(tmp_path / "tum", synth_frames(n=2))
    (src / "groundtruth.txt").write_text("1305031102.0 0 0 0 0 0 0\n")
    with pytest.raises(SceneError, match="groundtruth.txt:1: a TUM line has 8 numbers"):
        import_capture(src, align_floor=False)


def test_tum_freiburg_calibration_by_name(tmp_path):
    src = write_tum(tmp_path / "rgbd_dataset_freiburg1_xyz", synth_frames(n=2))
    (src / "camera-intrinsics.txt").unlink()
    s = tum.read(src)
    u = s.frames.undistortions[0]
    assert u is not None and u.K_raw.fx == 517.3
    # output camera = the valid rectangle (zoomed in, same size): no black corners
    assert s.intrinsics[0] == u.K_out and s.intrinsics[0].fx > 517.3
    assert s.frame(0).depth_m.shape == (30, 40)


def test_tum_fr1_undistortion_leaves_no_black_border(tmp_path):
    """A white, fully valid 640x480 fr1 frame stays white and valid everywhere after undistortion
    (into its own K it lost 5.3 % of the pixels to black corners)."""
    import numpy as np

    f = synth_frames(n=2, w=640, h=480)
    f.color[:] = 255
    f.depth_mm[:] = 1500
    src = write_tum(tmp_path / "rgbd_dataset_freiburg1_rpy", f)
    (src / "camera-intrinsics.txt").unlink()
    c, d = tum.read(src).frames.load(0)
    assert (c.min(axis=2) > 0).all() and (d > 0).all()
    K = tum.valid_rectangle_intrinsics(tum.Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
                                       tum.FREIBURG["freiburg1"][1])
    assert abs(K.fx - 546.75) < 0.05 and abs(K.fy - 543.09) < 0.05


# ---- COLMAP -----------------------------------------------------------------------------------
@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE"])
def test_colmap(tmp_path, binary, model):
    f = synth_frames(n=3)
    if model == "SIMPLE_PINHOLE":
        from dataclasses import replace

        f = replace(f, K=replace(f.K, fy=f.K.fx))
    src = write_colmap(tmp_path / "colmap", f, binary=binary, model=model)
    assert detect_format(src) == "colmap"
    s = import_capture(src, align_floor=False)
    assert s.frame_ids == ["img_0000.png", "img_0001.png", "img_0002.png"]
    _assert_frames_equal(s, f)
    assert any("2 sparse COLMAP points" in n for n in s.meta.notes)


def test_colmap_text_equals_binary_and_png_depth(tmp_path):
    f = synth_frames(n=3)
    a = import_capture(write_colmap(tmp_path / "t", f, binary=False, npy_depth=False), align_floor=False)
    b = import_capture(write_colmap(tmp_path / "b", f, binary=True), align_floor=False)
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    assert a.intrinsics == b.intrinsics
    np.testing.assert_allclose(a.frames.load(1)[1], b.frames.load(1)[1], atol=1e-6)
    pa = colmap.read_points_text(tmp_path / "t" / "sparse" / "0" / "points3D.txt")
    pb = colmap.read_points_binary(tmp_path / "b" / "sparse" / "0" / "points3D.bin")
    np.testing.assert_array_equal(pa.xyz, pb.xyz)
    np.testing.assert_array_equal(pa.rgb, pb.rgb)


def test_colmap_opencv_undistorts(tmp_path):
    import cv2

    f = synth_frames(n=2, w=64, h=48)
    dist = (-0.2, 0.05, 0.001, -0.002)
    s = import_capture(write_colmap(tmp_path / "c", f, model="OPENCV", dist=dist), align_floor=False)
    c, d = s.frames.load(0)
    m1, m2 = cv2.initUndistortRectifyMap(f.K.K, np.array(dist), None, f.K.K, (64, 48), cv2.CV_32FC1)
    np.testing.assert_array_equal(c, cv2.remap(f.color[0], m1, m2, cv2.INTER_LINEAR))
    ref = cv2.remap(f.depth_m[0], m1, m2, cv2.INTER_NEAREST)
    np.testing.assert_array_equal(d, ref)
    # nearest interpolation: every output depth is one of the input depths (no blended values)
    assert np.isin(d[d > 0], f.depth_m[0]).all()


def test_colmap_unsupported_model_named(tmp_path):
    src = write_colmap(tmp_path / "c", synth_frames(n=2), model="SIMPLE_RADIAL")
    with pytest.raises(SceneError, match="SIMPLE_RADIAL is not supported"):
        import_capture(src, align_floor=False)


def test_colmap_truncated_binary(tmp_path):
    src = write_colmap(tmp_path / "c", synth_frames(n=2), binary=True)
    p = src / "sparse" / "0" / "images.bin"
    p.write_bytes(p.read_bytes()[:50])
    with pytest.raises(SceneError, match="images.bin: truncated"):
        import_capture(src, align_floor=False)


def test_colmap_missing_depth(tmp_path):
    src = write_colmap(tmp_path / "c", synth_frames(n=2))
    (src / "depths" / "img_0001.npy").unlink()
    with pytest.raises(SceneError, match="no depth map for image img_0001.png"):
        import_capture(src, align_floor=False)


# ---- nerfstudio -------------------------------------------------------------------------------
@pytest.mark.parametrize("per_frame", [False, True])
def test_nerfstudio(tmp_path, per_frame):
    f = synth_frames(n=3)
    src = write_nerfstudio(tmp_path / "ns", f, per_frame_intrinsics=per_frame)
    assert detect_format(src) == "nerfstudio"
    s = import_capture(src, align_floor=False)
    _assert_frames_equal(s, f)
    # the OpenCV camera looks at the ring's target: +z axis points towards (0.1, -0.2, 0.3)
    z = s.T_world_cam[0, :3, 2]
    to_target = np.array([0.1, -0.2, 0.3]) - s.T_world_cam[0, :3, 3]
    assert z @ to_target / np.linalg.norm(to_target) == pytest.approx(1.0)


def test_nerfstudio_npy_depth_scale_and_json_file(tmp_path):
    f = synth_frames(n=2)
    src = write_nerfstudio(tmp_path / "ns", f, npy_depth=True)
    meta = json.loads((src / "transforms.json").read_text())
    meta["depth_unit_scale_factor"] = 0.001
    (src / "transforms.json").write_text(json.dumps(meta))
    s = import_capture(src / "transforms.json", align_floor=False)
    np.testing.assert_allclose(s.frames.load(0)[1], f.depth_m[0], rtol=1e-6)


def test_nerfstudio_errors(tmp_path):
    src = write_nerfstudio(tmp_path / "ns", synth_frames(n=2))
    meta = json.loads((src / "transforms.json").read_text())
    del meta["frames"][1]["depth_file_path"]
    (src / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match=r"frames\[1\]: no depth_file_path"):
        import_capture(src, align_floor=False)
    (src / "transforms.json").write_text("{ broken")
    with pytest.raises(SceneError, match="transforms.json: corrupt JSON"):
        import_capture(src, align_floor=False)


# ---- BOP --------------------------------------------------------------------------------------
def test_bop_with_w2c_and_objects(tmp_path):
    f = synth_frames(n=3)
    src = write_bop(tmp_path / "ds" / "test" / "000001", f)
    assert detect_format(src) == "bop"
    s = import_capture(src, align_floor=False)
    assert s.frame_ids == ["000001", "000004", "000007"]
    _assert_frames_equal(s, f, depth_atol=1e-6)  # value * 0.1 mm: whole mm exact up to float32
    assert len(s.objects) == 1 and s.objects[0].obj_id == 7
    np.testing.assert_allclose(s.objects[0].T_world_obj, BOP_T_WORLD_OBJ, atol=1e-9)
    import trimesh

    m = trimesh.load(s.objects[0].model_path)
    assert m.bounds[1].max() == pytest.approx(0.1)  # 100 mm -> 0.1 m
    back = load_scene(save_scene(s, tmp_path / "scene"))
    assert back.objects[0].model_path == "objects/obj_000007.ply"
    np.testing.assert_array_equal(back.objects[0].T_world_obj, s.objects[0].T_world_obj)


def test_bop_without_w2c_uses_object_as_world(tmp_path):
    f = synth_frames(n=3)
    src = write_bop(tmp_path / "ds" / "test" / "000001", f, with_w2c=False)
    s = import_capture(src, align_floor=False)
    # world = the object's frame: T_world_cam = inv(T_world_obj) @ T_world_cam(true)
    from presim.geometry import compose, invert

    np.testing.assert_allclose(s.T_world_cam, compose(invert(BOP_T_WORLD_OBJ), f.T_world_cam), atol=1e-9)
    np.testing.assert_allclose(s.objects[0].T_world_obj, np.eye(4), atol=1e-9)


def test_bop_real_lmo_has_no_depth(shared_data):
    src = shared_data("lmo_scene000002") / "test" / "000002"
    assert detect_format(src) == "bop"
    with pytest.raises(SceneError, match="depth: no depth folder"):
        import_capture(src)


# ---- cross-format -----------------------------------------------------------------------------
def test_cross_format_same_scene(tmp_path):
    """The same frames written as TUM, nerfstudio, kinfu, COLMAP and BOP import to the same scene:
    poses to 1e-6, depth within each format's quantisation (all hold whole millimetres)."""
    f = synth_frames(n=4, seed=3)
    scenes = {
        "tum": import_capture(write_tum(tmp_path / "tum", f), align_floor=False),
        "nerfstudio": import_capture(write_nerfstudio(tmp_path / "ns", f), align_floor=False),
        "kinfu": import_capture(write_kinfu(tmp_path / "kf", f), align_floor=False),
        "colmap": import_capture(write_colmap(tmp_path / "cm", f, binary=True), align_floor=False),
        "bop": import_capture(write_bop(tmp_path / "ds" / "test" / "000001", f, objects=False), align_floor=False),
    }
    ref = scenes.pop("tum")
    for name, s in scenes.items():
        assert len(s) == len(ref), name
        np.testing.assert_allclose(s.T_world_cam, ref.T_world_cam, atol=1e-6, err_msg=name)
        for i in range(len(ref)):
            assert s.intrinsics[i].K == pytest.approx(ref.intrinsics[i].K, abs=1e-9), name
            c, d = s.frames.load(i)
            c0, d0 = ref.frames.load(i)
            np.testing.assert_array_equal(c, c0, err_msg=name)
            np.testing.assert_allclose(d, d0, atol=1e-6, rtol=0, err_msg=name)
    # and the saved scenes of two formats are identical arrays
    a = load_scene(save_scene(ref, tmp_path / "a"))
    b = load_scene(save_scene(scenes["nerfstudio"], tmp_path / "b"))
    np.testing.assert_allclose(a.frames.depth_m, b.frames.depth_m, atol=1e-6)
    np.testing.assert_array_equal(a.frames.color, b.frames.color)


def test_unknown_folder_lists_formats(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(ValueError, match="Known formats: kinfu"):
        import_capture(tmp_path / "x")
    with pytest.raises(ValueError, match="unknown capture format 'foo'"):
        import_capture(tmp_path / "x", fmt="foo")
