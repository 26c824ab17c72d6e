"""BOP reader: real LM-O files, PLY ASCII/binary round trips, unit conversion and clear errors."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from presim.datasets.bop_reader import (
    MM_TO_M, BopDataset, read_camera_json, read_models_info, read_scene_camera, read_scene_gt,
    read_scene_gt_info, read_test_targets,
)
from presim.formats.ply import read_ply

# ---- real data ---------------------------------------------------------------------------------

def test_lmo_dataset_listing_and_units(shared_data):
    lmo = shared_data("lmo_scene000002")
    ds = BopDataset(lmo)
    assert ds.scene_ids() == [2]
    assert len(ds.image_ids(2)) == 200
    assert ds.obj_ids() == [1, 5, 6, 8, 9, 10, 11, 12]
    info = ds.models_info()
    assert info[1].diameter_m == pytest.approx(0.102099)
    assert info[1].min_m[0] == pytest.approx(-0.0379343)
    # This copy does carry BOP's discrete symmetries for eggbox (10) and glue (11).
    assert info[10].is_symmetric and info[11].is_symmetric and not info[1].is_symmetric
    assert abs(info[10].symmetries_discrete[0][0, 3]) < 0.001  # mm -> m: 0.23 mm
    cam = ds.camera()
    assert (cam.K.width, cam.K.height) == (640, 480) and cam.K.fx == pytest.approx(572.4114)
    gt = ds.scene_gt(2)[3][0]
    assert gt.obj_id == 1
    np.testing.assert_allclose(gt.t_m2c_m, np.array([161.68945982, -113.74032768, 1112.83112737]) * 1e-3)
    T = gt.T_cam_obj
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    gi = ds.scene_gt_info(2)[3][0]
    assert gi.bbox_obj == (388, 164, 34, 45) and gi.visib_fract == pytest.approx(0.19964507542147295)
    assert len(ds.scene_gt_info(2)[3]) == len(ds.scene_gt(2)[3])
    targets = ds.test_targets()
    assert len(targets) == 1445 and targets[0].scene_id == 2 and targets[0].inst_count == 1
    assert ds.intrinsics(2, 3).cx == pytest.approx(325.2611)
    assert ds.read_rgb(2, 3).shape == (480, 640, 3)


def test_lmo_models_match_trimesh_and_info(shared_data):
    lmo = shared_data("lmo_scene000002")
    import trimesh

    ds = BopDataset(lmo)
    for obj_id in (1, 10):
        for ev in (False, True):  # models/ is ASCII, models_eval/ is binary little-endian
            path = ds.model_path(obj_id, eval=ev)
            ours = read_ply(path)
            ref = trimesh.load(path, process=False)
            np.testing.assert_allclose(ours.vertices, ref.vertices, atol=1e-4)
            np.testing.assert_array_equal(ours.faces, ref.faces)
        m = ds.model_mesh_m(obj_id)  # metres
        size = m.vertices.max(0) - m.vertices.min(0)
        np.testing.assert_allclose(size, ds.models_info()[obj_id].size_m, atol=2e-4)
    assert ds.model_mesh_m(1).colors is not None and ds.model_mesh_m(1).normals is not None
    assert ds.model_path(1, eval=True).parent.name == "models_eval"


# ---- PLY ---------------------------------------------------------------------------------------

def _write_ply(path: Path, pts: np.ndarray, faces: np.ndarray, fmt: str) -> None:
    header = (f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {len(pts)}\nproperty float x\n"
              f"property float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    if fmt == "ascii":
        body = "".join(f"{p[0]} {p[1]} {p[2]} 10 20 30\n" for p in pts)
        body += "".join(f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in faces)
        path.write_bytes(header.encode() + body.encode())
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        body = b"".join(struct.pack(e + "fffBBB", *p, 10, 20, 30) for p in pts)
        body += b"".join(struct.pack(e + "B" + "i" * len(f), len(f), *f) for f in faces)
        path.write_bytes(header.encode() + body)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_formats_round_trip(tmp_path, fmt):
    pts = np.array([[0, 0, 0], [100, 0, 0], [100, 50, 0], [0, 50, 0]], dtype=np.float32)
    faces = [[0, 1, 2], [0, 2, 3]]
    p = tmp_path / f"m_{fmt}.ply"
    _write_ply(p, pts, np.array(faces), fmt)
    m = read_ply(p)
    np.testing.assert_allclose(m.vertices, pts)
    np.testing.assert_array_equal(m.faces, faces)
    assert m.colors.tolist()[0] == [10, 20, 30]
    np.testing.assert_allclose(m.scaled(MM_TO_M).vertices, pts * MM_TO_M)


def test_ply_quads_are_fan_triangulated(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
    p = tmp_path / "quad.ply"
    _write_ply(p, pts, np.array([[0, 1, 2, 3]]), "binary_little_endian")
    np.testing.assert_array_equal(read_ply(p).faces, [[0, 1, 2], [0, 2, 3]])


def test_ply_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(ValueError, match="bad.ply.*not a PLY"):
        read_ply(bad)
    trunc = tmp_path / "trunc.ply"
    _write_ply(trunc, np.zeros((4, 3), np.float32), np.array([[0, 1, 2]]), "binary_little_endian")
    trunc.write_bytes(trunc.read_bytes()[:-20])
    with pytest.raises(ValueError, match="trunc.ply.*truncated"):
        read_ply(trunc)
    oob = tmp_path / "oob.ply"
    _write_ply(oob, np.zeros((3, 3), np.float32), np.array([[0, 1, 7]]), "ascii")
    with pytest.raises(ValueError, match="out of range"):
        read_ply(oob)


# ---- JSON readers ------------------------------------------------------------------------------

def _dump(path: Path, obj) -> Path:
    path.write_text(json.dumps(obj))
    return path


def test_json_readers_convert_units(tmp_path):
    R = np.eye(3).reshape(-1).tolist()
    sc = read_scene_camera(_dump(tmp_path / "scene_camera.json", {
        "0": {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": 0.1,
              "cam_R_w2c": R, "cam_t_w2c": [1000, 0, -500]},
        "1": {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1]}}))
    assert sc[0].depth_scale == 0.1 and sc[1].depth_scale == 1.0 and sc[1].T_cam_world is None
    np.testing.assert_allclose(sc[0].T_cam_world[:3, 3], [1.0, 0.0, -0.5])
    gt = read_scene_gt(_dump(tmp_path / "scene_gt.json", {"0": [{"cam_R_m2c": R, "cam_t_m2c": [0, 0, 800], "obj_id": 3}]}))
    assert gt[0][0].obj_id == 3 and gt[0][0].T_cam_obj[2, 3] == pytest.approx(0.8)
    mi = read_models_info(_dump(tmp_path / "models_info.json", {"3": {
        "diameter": 200, "min_x": -10, "min_y": -20, "min_z": -30, "size_x": 20, "size_y": 40, "size_z": 60,
        "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 10]}]}}))
    assert mi[3].diameter_m == pytest.approx(0.2)
    axis, offset = mi[3].symmetries_continuous[0]
    np.testing.assert_allclose(axis, [0, 0, 1])
    np.testing.assert_allclose(offset, [0, 0, 0.01])
    cam = read_camera_json(_dump(tmp_path / "camera.json", {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 4, "height": 3}))
    assert cam.depth_scale == 1.0 and cam.K.height == 3
    tt = read_test_targets(_dump(tmp_path / "t.json", [{"scene_id": 1, "im_id": 2, "obj_id": 3, "inst_count": 2}]))
    assert tt[0].inst_count == 2


@pytest.mark.parametrize("content, match", [
    ({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0], "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}, "image 0 instance 0 cam_R_m2c.*9 numbers"),
    ({"0": [{"cam_R_m2c": [2, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}, "not a rotation"),
    ({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1]}]}, "missing field 'obj_id'"),
    ({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, "x", 1], "obj_id": 1}]}, "cam_t_m2c"),
    ({"abc": []}, "not an integer id"),
])
def test_scene_gt_errors(tmp_path, content, match):
    p = _dump(tmp_path / "scene_gt.json", content)
    with pytest.raises(ValueError, match=match) as ei:
        read_scene_gt(p)
    assert "scene_gt.json" in str(ei.value)


def test_missing_and_invalid_json(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene_gt_info.json"):
        read_scene_gt_info(tmp_path / "scene_gt_info.json")
    (tmp_path / "models_info.json").write_text("{broken")
    with pytest.raises(ValueError, match="models_info.json.*invalid JSON"):
        read_models_info(tmp_path / "models_info.json")
    _dump(tmp_path / "mi2.json", {"1": {"diameter": -3}})
    with pytest.raises(ValueError, match="diameter must be positive"):
        read_models_info(tmp_path / "mi2.json")
    with pytest.raises(FileNotFoundError, match="BOP dataset folder"):
        BopDataset(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="split folder"):
        BopDataset(tmp_path).scene_ids()


def test_depth_read_in_metres(tmp_path):
    from presim.io_utils import write_png

    sd = tmp_path / "test" / "000001"
    (sd / "depth").mkdir(parents=True)
    _dump(sd / "scene_camera.json", {"5": {"cam_K": [500, 0, 1.5, 0, 500, 1, 0, 0, 1], "depth_scale": 0.1}})
    write_png(sd / "depth" / "000005.png", np.array([[0, 10000, 20000, 65535]] * 3, np.uint16))
    ds = BopDataset(tmp_path)
    d = ds.read_depth_m(1, 5)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d[0, :3], [0.0, 1.0, 2.0], rtol=1e-6)  # png * 0.1 mm -> m
    assert ds.scene_ids() == [1] and ds.image_ids(1) == [5]
    assert ds.intrinsics(1, 5).width == 4  # no camera.json: size from the image
