"""Frame tree edge cases: fixed joints static, camera frames outside the URDF, extra root links."""

from __future__ import annotations

import dataclasses

import numpy as np

from presim.geometry import compose, invert, make_pose, rotation_z
from presim.outputs.frames import build_frame_tree, urdf_fixed_children
from presim.testing.steps import synthetic_info, synthetic_steps


def test_fixed_joints_are_static_and_chain_composes():
    info = synthetic_info()
    assert urdf_fixed_children(info.urdf_xml) == {"camera_link", "camera_optical_frame"}
    assert urdf_fixed_children("<not xml") == set()
    tree = build_frame_tree(info)
    r = next(synthetic_steps(1, drift_m=0.0))
    dyn, static = tree.edges(r)
    assert [(e.parent, e.child) for e in dyn[:2]] == [("map", "odom"), ("odom", "base_link")]
    assert {e.child for e in static} == {"camera_link", "camera_optical_frame"}
    edges = {e.child: e for e in dyn + static}
    T, f = np.eye(4), "camera_optical_frame"
    while f != "map":
        T, f = compose(edges[f].T_parent_child, T), edges[f].parent
    np.testing.assert_allclose(T, r.cameras[0].T_world_cam, atol=1e-12)


def test_camera_outside_urdf_and_extra_root_hang_off_base_link():
    info = synthetic_info()
    r = next(synthetic_steps(1))
    T_world_cam = compose(r.T_world_base, make_pose(rotation_z(0.3), [0.1, 0.2, 1.0]))
    cam = dataclasses.replace(r.cameras[0], frame_id="wrist_optical_frame", T_world_cam=T_world_cam)
    poses = dict(r.link_poses, lidar=make_pose(np.eye(3), [0, 0, 0.5]))
    r2 = dataclasses.replace(r, cameras=(cam,), link_poses=poses)
    dyn, _ = build_frame_tree(info).edges(r2)
    by_child = {e.child: e for e in dyn}
    assert by_child["wrist_optical_frame"].parent == "base_link"
    np.testing.assert_allclose(compose(r.T_world_base, by_child["wrist_optical_frame"].T_parent_child),
                               T_world_cam, atol=1e-12)
    assert by_child["lidar"].parent == "base_link" and by_child["lidar"].T_parent_child[2, 3] == 0.5
    np.testing.assert_allclose(compose(by_child["odom"].T_parent_child, invert(invert(r.odometry.T_odom_base))),
                               r.T_world_base, atol=1e-12)
