"""Robots from URDF: FK with hand-computed answers, yourdfpy agreement, user URDFs, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from presim.sim.robot import (DEFAULT_ROBOT_URDF, RobotConfig, T_BODY_OPTICAL, default_robot, free_camera_rig,
                              load_robot)

USER_URDF = """<?xml version="1.0"?>
<robot name="user_bot">
  <link name="chassis">
    <collision><origin xyz="0 0 0.1"/><geometry><box size="0.6 0.4 0.2"/></geometry></collision>
  </link>
  <joint name="mast" type="prismatic">
    <parent link="chassis"/><child link="top"/>
    <origin xyz="0.1 0 0.5"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="1" velocity="0.1"/>
  </joint>
  <link name="top"/>
  <joint name="cam_mount" type="fixed">
    <parent link="top"/><child link="front_cam"/>
    <origin xyz="0.05 0 0.2" rpy="0 0 0"/>
  </joint>
  <link name="front_cam"/>
</robot>
"""


def test_default_robot_fk_camera_where_urdf_says():
    robot = default_robot()
    assert robot.joint_names == ("head_pan_joint", "head_tilt_joint")
    # Zero joints: pan joint at z=1.00, tilt +0.05, camera +0.08 forward +0.05 up -> (0.08, 0, 1.10).
    T = robot.T_base_camera(np.zeros(2))
    assert np.allclose(T[:3, 3], [0.08, 0.0, 1.10], atol=1e-12)
    # Optical axes: z forward (= base +x), x right (= base -y), y down (= base -z).
    assert np.allclose(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    # Pan by +90 deg: the camera swings to the robot's left, looking along +y.
    T = robot.T_base_camera(np.array([np.pi / 2, 0.0]))
    assert np.allclose(T[:3, 3], [0.0, 0.08, 1.10], atol=1e-12)
    assert np.allclose(T[:3, 2], [0, 1, 0], atol=1e-12)
    # Tilt by +30 deg (looks down): the camera offset (0.08, 0, 0.05) rotates about y at z=1.05.
    a = np.radians(30)
    T = robot.T_base_camera(np.array([0.0, a]))
    expect = [0.08 * np.cos(a) + 0.05 * np.sin(a), 0.0, 1.05 - 0.08 * np.sin(a) + 0.05 * np.cos(a)]
    assert np.allclose(T[:3, 3], expect, atol=1e-12)
    assert np.allclose(T[:3, 2], [np.cos(a), 0, -np.sin(a)], atol=1e-12)  # optical axis points down
    assert robot.footprint_radius_m == pytest.approx(0.25)
    assert robot.height_m == pytest.approx(1.15)  # head box top: 1.05 + 0.05 + 0.05


def test_fk_matches_yourdfpy():
    import yourdfpy

    robot = default_robot()
    u = yourdfpy.URDF.load(str(DEFAULT_ROBOT_URDF), load_meshes=False)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform(robot.lower, robot.upper)
        u.update_cfg(q)
        poses = robot.fk(q)
        for link in robot.links:
            assert np.allclose(poses[link], u.get_transform(link, "base_link"), atol=1e-9), link


def test_fk_at_unchanged_joints_gives_fresh_equal_poses():
    """A robot that keeps its joints still gets the last poses again (cached), as new arrays: what a
    caller does to them does not reach the next call; other joint values are computed anew."""
    robot = default_robot()
    q = np.array([0.3, -0.2])
    a = robot.fk(q)
    b = robot.fk(q.copy())
    assert a.keys() == b.keys()
    for link in a:
        np.testing.assert_array_equal(a[link], b[link])
        assert not np.shares_memory(a[link], b[link])
    b["camera_optical_frame"][:] = 0.0  # the caller's own copy
    np.testing.assert_array_equal(robot.fk(q)["camera_optical_frame"], a["camera_optical_frame"])
    c = robot.fk(np.array([0.0, 0.0]))
    assert not np.allclose(c["camera_optical_frame"], a["camera_optical_frame"])
    np.testing.assert_allclose(c["camera_optical_frame"], robot.T_base_camera(np.zeros(2)), atol=1e-12)


def test_free_camera_rig():
    rig = free_camera_rig()
    assert rig.drive == "free" and rig.joint_names == ()
    assert np.allclose(rig.T_base_camera(), T_BODY_OPTICAL)


def test_user_urdf_with_named_body_camera_link(tmp_path):
    p = tmp_path / "user.urdf"
    p.write_text(USER_URDF)
    robot = load_robot(p, RobotConfig(drive="holonomic", camera_link="front_cam", camera_link_is_optical=False))
    assert robot.root == "chassis" and robot.joint_names == ("mast",)
    assert robot.footprint_radius_m == pytest.approx(np.hypot(0.3, 0.2))
    T = robot.T_base_camera(np.array([0.2]))
    assert np.allclose(T[:3, 3], [0.15, 0.0, 0.9])  # prismatic mast raised by 0.2
    assert np.allclose(T[:3, :3], T_BODY_OPTICAL[:3, :3])
    # Velocity and position limits come from the URDF.
    assert robot.velocity_limits[0] == pytest.approx(0.1) and robot.upper[0] == pytest.approx(0.3)


def test_unknown_links_and_joints_are_clear_errors(tmp_path):
    p = tmp_path / "user.urdf"
    p.write_text(USER_URDF)
    with pytest.raises(ValueError, match="camera link 'nope'.*chassis"):
        load_robot(p, RobotConfig(camera_link="nope"))
    robot = load_robot(p, RobotConfig(camera_link="front_cam"))
    with pytest.raises(ValueError, match="unknown or fixed joint 'elbow'"):
        robot.joint_index("elbow")
    with pytest.raises(ValueError, match="unknown or fixed joint 'cam_mount'"):
        robot.joint_index("cam_mount")
    with pytest.raises(ValueError, match="unknown link 'wheel'"):
        robot.check_link("wheel")
    with pytest.raises(ValueError, match="unknown or fixed joint 'wrist'"):
        load_robot(p, RobotConfig(camera_link="front_cam", initial_joint_positions=(("wrist", 1.0),)))


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.urdf"):
        load_robot(tmp_path / "missing.urdf")
    x = tmp_path / "robot.urdf.xacro"
    x.write_text('<robot xmlns:xacro="http://ros.org/wiki/xacro" name="r"><link name="$(arg prefix)base"/></robot>')
    with pytest.raises(ValueError, match="xacro"):
        load_robot(x)
    b = tmp_path / "broken.urdf"
    b.write_text("<robot name='r'><link name='a'></robot")
    with pytest.raises(ValueError, match="broken.urdf"):
        load_robot(b)
    with pytest.raises(ValueError, match="unknown drive"):
        load_robot(DEFAULT_ROBOT_URDF, RobotConfig(drive="tank"))
