"""BOP records (presim.formats.bop): each record's JSON entry read back gives the same record, with
hand-computed millimetre values; the BOP importer reports bad JSON through the same readers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from presim.datasets.bop_writer import bop_json_text
from presim.datasets.objects import ObjectModel, models_info_entry
from presim.formats.bop import (
    M_TO_MM, MM_TO_M, BopCamera, GtInfo, GtInstance, SceneCamera, load_json, read_camera_json,
    read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info,
)
from presim.geometry import Intrinsics, make_pose

RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def test_gt_instance_json_in_millimetres_and_back(tmp_path):
    gt = GtInstance.from_pose(5, make_pose(RZ90, [0.1, -0.02, 0.5]))
    e = gt.to_json()
    assert e == {"cam_R_m2c": [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                 "cam_t_m2c": [100.0, -20.0, 500.0], "obj_id": 5}
    (tmp_path / "scene_gt.json").write_text(bop_json_text({"3": [e, e]}))
    back = read_scene_gt(tmp_path / "scene_gt.json")
    assert list(back) == [3] and len(back[3]) == 2
    b = back[3][1]
    assert b.obj_id == 5
    np.testing.assert_array_equal(b.R_m2c, RZ90)
    np.testing.assert_allclose(b.t_m2c_m, [0.1, -0.02, 0.5], rtol=1e-15)
    np.testing.assert_allclose(b.T_cam_obj, gt.T_cam_obj, rtol=1e-15)


def test_gt_info_json_round_trip_is_exact(tmp_path):
    info = GtInfo(bbox_obj=(10, 20, 30, 40), bbox_visib=(12, 20, 28, 35), px_count_all=900,
                  px_count_valid=850, px_count_visib=720, visib_fract=0.8)
    e = info.to_json()
    assert e == {"bbox_obj": [10, 20, 30, 40], "bbox_visib": [12, 20, 28, 35], "px_count_all": 900,
                 "px_count_valid": 850, "px_count_visib": 720, "visib_fract": 0.8}
    (tmp_path / "scene_gt_info.json").write_text(bop_json_text({"0": [e]}))
    assert read_scene_gt_info(tmp_path / "scene_gt_info.json") == {0: [info]}


def test_scene_camera_json_round_trip(tmp_path):
    K = np.array([[500.0, 0, 319.5], [0, 510.0, 239.5], [0, 0, 1]])
    cam = SceneCamera(K=K, depth_scale=0.1, T_cam_world=make_pose(RZ90, [1.0, 2.0, -0.25]))
    e = cam.to_json()
    assert e["cam_t_w2c"] == [1000.0, 2000.0, -250.0] and e["depth_scale"] == 0.1
    assert list(e) == ["cam_K", "cam_R_w2c", "cam_t_w2c", "depth_scale"]  # bop_toolkit's key order
    no_pose = SceneCamera(K=K, depth_scale=1.0)
    assert list(no_pose.to_json()) == ["cam_K", "depth_scale"]
    (tmp_path / "scene_camera.json").write_text(bop_json_text({"7": e, "8": no_pose.to_json()}))
    back = read_scene_camera(tmp_path / "scene_camera.json")
    np.testing.assert_array_equal(back[7].K, K)
    np.testing.assert_allclose(back[7].T_cam_world, cam.T_cam_world, rtol=1e-15)
    assert back[8].T_cam_world is None and back[8].depth_scale == 1.0


def test_camera_json_round_trip(tmp_path):
    cam = BopCamera(K=Intrinsics(572.4114, 573.57043, 325.2611, 242.04899, 640, 480), depth_scale=0.1)
    (tmp_path / "camera.json").write_text(json.dumps(cam.to_json()))
    assert read_camera_json(tmp_path / "camera.json") == cam


def test_models_info_entry_read_back_in_metres(tmp_path):
    """A 100 x 60 x 40 mm box centred at the origin with a 180 deg symmetry about z (10 mm offset)."""
    import trimesh

    box = trimesh.creation.box((0.1, 0.06, 0.04))
    S = make_pose(np.diag([-1.0, -1.0, 1.0]), [0.0, 0.0, 0.01])
    model = ObjectModel(3, "box", np.asarray(box.vertices), np.asarray(box.faces), symmetries_discrete=(S,),
                        symmetries_continuous=(((0.0, 0.0, 1.0), (0.0, 0.0, 0.002)),))
    e = models_info_entry(model)
    # diameter = the box diagonal sqrt(100^2 + 60^2 + 40^2) = sqrt(15200) = 123.2883 mm
    assert e["diameter"] == pytest.approx(123.2883, abs=1e-4)
    assert (e["min_x"], e["min_y"], e["min_z"]) == pytest.approx((-50.0, -30.0, -20.0))
    assert e["symmetries_discrete"][0][11] == pytest.approx(10.0)           # t_z in mm
    assert e["symmetries_continuous"][0]["offset"] == pytest.approx([0.0, 0.0, 2.0])
    (tmp_path / "models_info.json").write_text(json.dumps({"3": e}))
    info = read_models_info(tmp_path / "models_info.json")[3]
    assert info.diameter_m == pytest.approx(0.1232883, abs=1e-7)
    np.testing.assert_allclose(info.min_m, [-0.05, -0.03, -0.02], atol=1e-9)
    np.testing.assert_allclose(info.size_m, [0.1, 0.06, 0.04], atol=1e-9)
    np.testing.assert_allclose(info.symmetries_discrete[0], S, atol=1e-12)
    np.testing.assert_allclose(info.symmetries_continuous[0][1], [0, 0, 0.002], atol=1e-12)
    assert info.is_symmetric


def test_units_and_loader():
    assert MM_TO_M * M_TO_MM == 1.0 and 250.0 * MM_TO_M == 0.25


def test_json_loader_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json: file not found"):
        load_json(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="bad.json: invalid JSON"):
        load_json(tmp_path / "bad.json")


def test_bop_importer_errors_come_from_the_shared_readers(tmp_path):
    from presim.capture.importers import bop
    from presim.capture.scene import SceneError

    (tmp_path / "depth").mkdir()
    (tmp_path / "scene_camera.json").write_text("{not json")
    with pytest.raises(SceneError, match="scene_camera.json: invalid JSON"):
        bop.read(tmp_path)
    (tmp_path / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [1, 0, 0]}}))
    with pytest.raises(SceneError, match=r"scene_camera.json: image 0 cam_K: expected 9 numbers, got 3"):
        bop.read(tmp_path)
    (tmp_path / "scene_camera.json").write_text(json.dumps({"x": {"cam_K": [1] * 9}}))
    with pytest.raises(SceneError, match="key 'x' is not an integer id"):
        bop.read(tmp_path)
