"""Camera pose sampling around seed views (thesis §5.3.6): bounds, determinism, candidate checks;
object sources (BOP scene_gt, YCB-Video meta.mat) placed in a scene's world."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from presim.datasets.camera_sampling import (
    CameraSamplingConfig, check_candidate, frame_rng, output_intrinsics, perturb_pose,
)
from presim.geometry import Intrinsics, compose, invert, look_at, rotation_angle_rad


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), slot=st.integers(0, 10_000), attempt=st.integers(0, 50))
def test_perturbation_stays_within_bounds(seed, slot, attempt):
    cfg = CameraSamplingConfig()
    T_seed = look_at([1.0, -2.0, 1.2], [0.0, 0.0, 0.8])
    T = perturb_pose(frame_rng(seed, slot, attempt), T_seed, cfg)
    T_seed_cam = compose(invert(T_seed), T)  # the move in the seed camera's own frame
    assert np.degrees(rotation_angle_rad(T_seed_cam[:3, :3])) <= cfg.max_rotation_deg + 1e-9
    assert np.linalg.norm(T_seed_cam[:3, 3]) <= cfg.max_translation_m + 1e-12
    # Roll is limited: the rotated camera's x axis stays close to the seed's image plane.
    R = T_seed_cam[:3, :3]
    roll_deg = np.degrees(np.arctan2(R[1, 0], R[0, 0]))
    assert abs(roll_deg) <= cfg.max_roll_deg + 1.0 + 0.5 * cfg.max_rotation_deg * np.sin(np.radians(cfg.max_rotation_deg))


def test_sampling_is_deterministic_and_varied():
    T_seed = look_at([1.0, -2.0, 1.2], [0.0, 0.0, 0.8])
    a = perturb_pose(frame_rng(0, 5, 0), T_seed)
    b = perturb_pose(frame_rng(0, 5, 0), T_seed)
    c = perturb_pose(frame_rng(0, 6, 0), T_seed)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    moves = [compose(invert(T_seed), perturb_pose(frame_rng(1, k, 0), T_seed)) for k in range(300)]
    ang = np.degrees([rotation_angle_rad(m[:3, :3]) for m in moves])
    dist = [np.linalg.norm(m[:3, 3]) for m in moves]
    # They fill the allowed range, not a corner of it.
    assert ang.max() > 25 and np.median(ang) > 8 and max(dist) > 0.17


def test_candidate_checks_name_the_reason():
    cfg = CameraSamplingConfig()
    from types import SimpleNamespace

    from presim.capture.scene import FloorPlane

    scene = SimpleNamespace(floor=FloorPlane((0.0, 0.0, 1.0), 0.0))
    T = look_at([1.0, 0.0, 1.0], [0.0, 0.0, 0.8])
    c = np.array([0.0, 0.0, 0.8])
    assert check_candidate(T, 500, 600, c, 0.1, scene, None, cfg) is None
    assert check_candidate(T, 10, 600, c, 0.1, scene, None, cfg) == "target_out_of_view"
    assert check_candidate(T, 200, 600, c, 0.1, scene, None, cfg) == "target_truncated"
    assert check_candidate(look_at([0.05, 0.0, 0.8], [0, 1, 0.8]), 500, 600, c, 0.1, scene, None, cfg) == "too_close"
    assert check_candidate(look_at([1.0, 0.0, -0.1], c), 500, 600, c, 0.1, scene, None, cfg) == "below_floor"
    from scipy.spatial import cKDTree

    tree = cKDTree(np.array([[1.0, 0.0, 1.05]]))
    assert check_candidate(T, 500, 600, c, 0.1, scene, tree, cfg) == "inside_geometry"


def test_output_intrinsics_keep_horizontal_fov():
    K = Intrinsics.from_fov(640, 480, 62.0)
    Ko = output_intrinsics(K, 1280, 720)
    assert Ko.width == 1280 and Ko.height == 720
    assert abs(Ko.hfov_deg - 62.0) < 1e-9 and Ko.fx == Ko.fy
    assert abs(output_intrinsics(K, 1280, 720, hfov_deg=90.0).hfov_deg - 90.0) < 1e-9


# ---- object sources (BOP scene_gt, YCB-Video meta.mat) placed in a PreSim scene's world ----------

def _fake_scene(frame_ids):
    from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
    from presim.geometry import make_pose, quat_xyzw_to_R

    rng = np.random.default_rng(0)
    n = len(frame_ids)
    T = np.stack([make_pose(quat_xyzw_to_R(rng.normal(size=4)), rng.normal(size=3)) for _ in range(n)])
    K = Intrinsics(500.0, 500.0, 15.5, 11.5, 32, 24)
    frames = ArrayFrameSource(np.zeros((n, 24, 32, 3), np.uint8), np.zeros((n, 24, 32), np.float32))
    return Scene(list(frame_ids), np.arange(n, dtype=float), T, [K] * n, frames, SceneMeta("fake", "test"))


def test_objects_from_bop_scene_gt_placed_by_frame(shared_data):
    import json

    import pytest

    from presim.datasets.object_sources import resolve_objects

    lmo = shared_data("lmo_scene000002")
    scene = _fake_scene(["000003", "000008", "000017"])
    objs = resolve_objects(scene, f"bop:{lmo / 'test' / '000002'}")
    gt = json.loads((lmo / "test/000002/scene_gt.json").read_text())
    assert [o.obj_id for o in objs] == sorted({g["obj_id"] for g in gt["3"]})
    for o in objs:
        g = next(g for g in gt["3"] if g["obj_id"] == o.obj_id)
        T_cam_obj = compose(invert(scene.T_world_cam[0]), o.T_world_obj)
        assert np.allclose(T_cam_obj[:3, 3] * 1000, g["cam_t_m2c"], atol=1e-6)
        assert np.allclose(T_cam_obj[:3, :3].ravel(), g["cam_R_m2c"], atol=1e-6)
        assert o.model.vertices_m.max() < 0.2  # mm converted to metres
    assert objs[[o.obj_id for o in objs].index(10)].model.symmetric  # eggbox: models_info symmetry
    with pytest.raises(ValueError, match="image 3 is not among"):
        resolve_objects(_fake_scene(["000004"]), f"bop:{lmo / 'test' / '000002'}")


def test_objects_from_ycbv_meta(shared_data):
    import pytest
    import scipy.io

    from presim.datasets.object_sources import resolve_objects

    ycb = shared_data("ycbv_2frames")
    scene = _fake_scene(["000001", "000002"])
    objs = resolve_objects(scene, f"ycbv:{ycb}")
    meta = scipy.io.loadmat(ycb / "data/000001-meta.mat")
    cls = meta["cls_indexes"].ravel()
    assert {int(c) for c in cls} <= {o.obj_id for o in objs}
    o = next(o for o in objs if o.obj_id == int(cls[0]))
    T_cam_obj = compose(invert(scene.T_world_cam[0]), o.T_world_obj)
    assert np.allclose(T_cam_obj[:3, :4], meta["poses"][:, :, 0], atol=1e-9)
    assert o.model.faces is None and len(o.model.vertices_m) > 1000  # points.xyz model
