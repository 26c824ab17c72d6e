"""Step loop: kinematics with known answers, collisions against walls, determinism, camera rate, sinks,
joints, free rig replay on a real tabletop capture."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from presim.capture.scene import Scene
from presim.geometry import compose
from presim.sensors.camera import CameraSpec
from presim.sensors.noise import DepthNoiseConfig
from presim.sensors.odometry import OdometryConfig
from presim.sim.controllers import Action, BaseLimits, TrajectoryReplay, joint_position_step
from presim.sim.robot import RobotConfig, default_robot, load_robot
from presim.sim.simulator import SimConfig, Simulator
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")
FAST = BaseLimits(max_acc_mps2=1e6, max_ang_acc_radps2=1e6, max_vx_mps=2.0, max_wz_radps=2.0)


@pytest.fixture(scope="module")
def toy() -> Scene:
    return build_toy_room(ToyRoomConfig(width=80, height=60))


@pytest.fixture(scope="module")
def sample_small(tmp_path_factory) -> Path:
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    dst = tmp_path_factory.mktemp("sample") / "scene"
    return build_sample_scene(dst, seed=0, config=SampleSceneConfig(width=160, height=120, num_frames=30))


def test_straight_twist_moves_by_integrated_amount(toy):
    sim = Simulator(toy, default_robot(), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    sim.reset(0, start=np.array([1.0, 1.0, 0.0]))
    for _ in range(20):
        r = sim.step(np.array([0.4, 0.0, 0.0]))
    assert np.allclose(r.T_world_base[:3, 3], [1.8, 1.0, 0.0], atol=1e-9)  # 0.4 m/s * 2 s
    assert not r.contact and np.allclose(r.applied_command, [0.4, 0, 0])
    # With acceleration limits the base moves by the integral of the applied (ramped) command.
    sim = Simulator(toy, default_robot(), SimConfig(dt_s=0.1, cameras=()))
    sim.reset(0, start=np.array([1.0, 1.0, 0.0]))
    applied = [sim.step(np.array([0.4, 0.0, 0.0])).applied_command[0] for _ in range(20)]
    assert np.allclose(applied[:4], [0.1, 0.2, 0.3, 0.4])  # 1 m/s^2 default
    assert sim.T_world_base[0, 3] == pytest.approx(1.0 + 0.1 * sum(applied), abs=1e-9)
    assert sim.T_world_base[0, 3] == pytest.approx(1.74, abs=1e-9)


def test_arc_twist_moves_on_the_circle(toy):
    n = 40
    sim = Simulator(toy, default_robot(), SimConfig(dt_s=np.pi / n, cameras=(), limits=FAST))
    sim.reset(0, start=np.array([1.0, 1.0, 0.0]))
    for _ in range(n):  # v = w = 0.5 for pi s: quarter circle of radius 1
        r = sim.step(np.array([0.5, 0.0, 0.5]))
    assert np.allclose(r.T_world_base[:3, 3], [2.0, 2.0, 0.0], atol=1e-9)
    assert np.allclose(r.T_world_base[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-9)
    assert r.sim_time_s == pytest.approx(np.pi)
    # Odometry (no drift) integrates the same motion in the odom frame (= start pose).
    assert np.allclose(r.odometry.T_odom_base[:3, 3], [1.0, 1.0, 0.0], atol=1e-9)


def test_diff_drive_ignores_vy_holonomic_uses_it(toy):
    sim = Simulator(toy, default_robot("diff"), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    sim.reset(0, start=np.array([1.0, 1.0, 0.0]))
    r = sim.step(np.array([0.0, 0.3, 0.0]))
    assert np.allclose(r.applied_command, 0) and np.allclose(r.T_world_base[:2, 3], [1.0, 1.0])
    sim = Simulator(toy, default_robot("holonomic"), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    sim.reset(0, start=np.array([1.0, 1.0, np.pi / 2]))
    r = sim.step(np.array([0.0, 0.3, 0.0]))  # left of a base facing +y is -x
    assert np.allclose(r.applied_command, [0, 0.3, 0]) and np.allclose(r.T_world_base[:2, 3], [0.97, 1.0])


def test_toy_pillar_stops_base_at_footprint_distance(toy):
    sim = Simulator(toy, default_robot(), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    sim.reset(0, start=np.array([2.5, 2.0, 0.0]))
    contacts = [sim.step(np.array([0.6, 0.0, 0.0])).contact for _ in range(40)]
    assert any(contacts)
    x = sim.T_world_base[0, 3]
    # Pillar face at x = 3.4; the base (radius 0.25) stops within one cell of touching it.
    assert 3.4 - 0.25 - 0.05 - 1e-9 <= x <= 3.4 - 0.25


def test_base_cannot_pass_through_a_wall_of_the_sample_scene(sample_small):
    from presim.capture.store import load_scene

    scene = load_scene(sample_small)
    sim = Simulator(scene, default_robot(), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    occ = sim.occupancy
    wall_x = float(scene.points.xyz[:, 0].min())  # west wall surface
    # Head west from free cells in the room's middle band, straight and at an angle (slides).
    starts = [(0.0, y) for y in np.linspace(-1.2, 1.2, 7) if not occ.is_blocked(0.0, y)]
    assert starts
    slides = []
    for x0, y0 in starts[:3]:
        for yaw in (np.pi, np.pi - 0.4):
            sim.reset(0, start=np.array([x0, y0, yaw]))
            first_contact_y = None
            for _ in range(100):
                r = sim.step(np.array([1.0, 0.0, 0.0]))
                x, y = r.T_world_base[:2, 3]
                if r.contact and first_contact_y is None:
                    first_contact_y = y
                assert x - 0.25 >= wall_x - 1e-9, "base crossed the wall"
                assert occ.distance(x, y) >= 0.25, "base overlaps an obstacle"
            assert first_contact_y is not None, "driving at the wall never reported contact"
            if yaw != np.pi:
                slides.append(y - first_contact_y)
    # At an angle the base slides along the wall (towards +y here) instead of sticking to it.
    assert max(slides) > 0.2


def test_same_seed_same_trajectory_and_images(toy):
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=32, height=24, rate_hz=10, noise=DepthNoiseConfig()),),
                    odometry=OdometryConfig(drift=True))

    def run(seed):
        sim = Simulator(toy, default_robot(), cfg)
        out = [sim.reset(seed)]
        for k in range(6):
            out.append(sim.step(np.array([0.3, 0.0, 0.4 * np.sin(k)])))
        return out

    a, b, c = run(5), run(5), run(6)
    for ra, rb in zip(a, b):
        assert np.array_equal(ra.T_world_base, rb.T_world_base)
        assert np.array_equal(ra.odometry.T_odom_base, rb.odometry.T_odom_base)
        assert np.array_equal(ra.cameras[0].color, rb.cameras[0].color)
        assert np.array_equal(ra.cameras[0].depth_m, rb.cameras[0].depth_m)
    assert not np.array_equal(a[0].T_world_base, c[0].T_world_base) or \
        not np.array_equal(a[-1].cameras[0].depth_m, c[-1].cameras[0].depth_m)


def test_camera_rate_pose_and_timings(toy):
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=32, height=24, rate_hz=5.0),))
    sim = Simulator(toy, default_robot(), cfg)
    results = [sim.reset(0)] + [sim.step(np.zeros(3)) for _ in range(6)]
    assert [len(r.cameras) for r in results] == [1, 0, 1, 0, 1, 0, 1]
    for r in results:
        for cam in r.cameras:
            assert cam.stamp_s == pytest.approx(r.sim_time_s)
            T = compose(r.T_world_base, r.link_poses["camera_optical_frame"])
            assert np.allclose(cam.T_world_cam, T)
            assert cam.color.shape == (24, 32, 3) and cam.depth_m.dtype == np.float32
            assert cam.T_world_cam[2, 3] == pytest.approx(1.10, abs=1e-9)  # camera height on the floor
    for key in ("control", "collision", "fk", "render", "sinks", "total"):
        assert key in results[2].timings_ms


def test_joint_targets_move_at_velocity_limit(toy):
    sim = Simulator(toy, default_robot(), SimConfig(dt_s=0.1, cameras=()))
    sim.reset(0, start=np.array([2.0, 2.0, 0.0]))
    r = sim.step(Action(twist=np.zeros(3), joint_targets={"head_pan_joint": 1.0, "head_tilt_joint": 0.5}))
    assert np.allclose(r.joint_states.position, [0.15, 0.1])  # URDF velocity limits 1.5 and 1.0 rad/s
    assert np.allclose(r.joint_states.velocity, [1.5, 1.0])
    for _ in range(10):
        r = sim.step(np.zeros(3))  # targets persist
    assert np.allclose(r.joint_states.position, [1.0, 0.5])
    # at the targets the joints stand still: the same positions as the joint controller's step of
    # 0 gives, velocities 0 (the step skips the controller there)
    q = r.joint_states.position.copy()
    want_q, want_qd = joint_position_step(q, sim.q_target, sim.robot.lower, sim.robot.upper,
                                          sim.robot.velocity_limits, 0.1)
    r = sim.step(np.zeros(3))
    np.testing.assert_array_equal(r.joint_states.position, want_q)
    np.testing.assert_array_equal(r.joint_states.velocity, want_qd)
    assert not want_qd.any()
    r = sim.step(Action(twist=np.zeros(3), joint_targets={"head_pan_joint": 0.9}))  # moves again
    assert r.joint_states.velocity[0] == pytest.approx(-1.0) and r.joint_states.position[0] == pytest.approx(0.9)
    with pytest.raises(ValueError, match="unknown or fixed joint 'elbow'"):
        sim.step(Action(joint_targets={"elbow": 0.1}))


def test_sinks_see_every_step_without_the_loop_knowing_them(toy):
    class Probe:
        def __init__(self):
            self.calls = []

        def open(self, info):
            self.calls.append(("open", info.scene_name, info.points_xyz.shape[1], "base_link" in info.urdf_xml))

        def on_step(self, result):
            self.calls.append(("step", result.step_idx))

        def close(self):
            self.calls.append(("close",))

    probe = Probe()
    sim = Simulator(toy, default_robot(), SimConfig(cameras=()))
    sim.add_sink(probe)
    sim.reset(0)
    sim.step(np.zeros(3))
    sim.step(np.zeros(3))
    sim.close()
    sim.close()
    assert probe.calls == [("open", "toy-room", 3, True), ("step", 0), ("step", 1), ("step", 2), ("close",)]


def test_outside_captured_area_is_reported(toy):
    sim = Simulator(toy, default_robot(), SimConfig(cameras=()))
    assert not sim.reset(0, start=np.array([2.5, 2.0, 0.0])).outside_captured_area
    assert sim.reset(0, start=np.array([-0.6, 2.0, 0.0])).outside_captured_area  # beyond the west wall


def test_floorless_scene_needs_the_free_rig(toy):
    import dataclasses

    scene = dataclasses.replace(toy, floor=None)
    with pytest.raises(ValueError, match="has no floor.*free camera rig"):
        Simulator(scene, default_robot(), SimConfig(cameras=()))
    assert Simulator(scene, None, SimConfig(cameras=())).is_free



def test_free_rig_replays_poses_exactly_on_the_tabletop_capture(shared_data):
    apc = shared_data("apc_cardboard_bin_kinfu50")
    from presim.capture.importers.registry import import_capture

    scene = import_capture(apc)
    assert scene.floor is None
    sim = Simulator(scene, None, SimConfig(dt_s=0.1, cameras=(CameraSpec(width=64, height=48),)))
    assert sim.is_free
    poses = scene.T_world_cam[10:16]
    rep = TrajectoryReplay(np.arange(len(poses)) * 0.1, poses)
    T_base_cam = sim.T_base_cam(0)
    r = sim.reset(0, start=compose(poses[0], np.linalg.inv(T_base_cam)))
    got = [r]
    for k in range(1, len(poses)):
        T = compose(rep.pose_at(0.1 * k), np.linalg.inv(T_base_cam))
        got.append(sim.step(Action(T_world_base=T)))
    for k, r in enumerate(got):
        assert np.allclose(r.cameras[0].T_world_cam, poses[k], atol=1e-9)
        assert r.cameras[0].depth_m.max() > 0 and not r.outside_captured_area
    # Velocity commands also fly it (6-DoF), with limits.
    r = sim.step(np.array([0.05, 0.0, 0.02, 0.0, 0.1, 0.0]))
    assert r.applied_command.shape == (3,) and not r.contact


BODY_CAM_URDF = """<?xml version="1.0"?>
<robot name="user_bot">
  <link name="chassis">
    <collision><origin xyz="0 0 0.1"/><geometry><cylinder radius="0.2" length="0.2"/></geometry></collision>
  </link>
  <joint name="cam_mount" type="fixed">
    <parent link="chassis"/><child link="front_cam"/><origin xyz="0.1 0 0.8" rpy="0 0.2 0"/>
  </joint>
  <link name="front_cam"/>
</robot>
"""


def test_user_urdf_with_named_body_camera_link(toy, tmp_path):
    from presim.sim.robot import T_BODY_OPTICAL

    p = tmp_path / "user.urdf"
    p.write_text(BODY_CAM_URDF)
    robot = load_robot(p, RobotConfig(drive="holonomic", camera_link="front_cam", camera_link_is_optical=False))
    sim = Simulator(toy, robot, SimConfig(cameras=(CameraSpec(width=32, height=24, hfov_deg=60),)))
    r = sim.reset(0, start=np.array([2.0, 2.0, 0.3]))
    cam = r.cameras[0]
    assert cam.frame_id == "front_cam"
    assert np.allclose(cam.T_world_cam, r.T_world_base @ r.link_poses["front_cam"] @ T_BODY_OPTICAL)
    assert cam.T_world_cam[2, 3] == pytest.approx(0.8)
    assert cam.depth_m.max() > 0


def test_random_driving_never_enters_an_obstacle(toy):
    """Property: whatever the commands, the footprint never overlaps an occupied cell and the base
    never leaves the walled room (seeded random twists, holonomic so it also strafes into walls)."""
    rng = np.random.default_rng(11)
    sim = Simulator(toy, default_robot("holonomic"), SimConfig(dt_s=0.1, cameras=(), limits=FAST))
    occ = sim.occupancy
    sim.reset(0, start=np.array([1.5, 2.0, 0.0]))
    contacts = 0
    for _ in range(400):
        r = sim.step(rng.uniform([-2.0, -0.4, -2.0], [2.0, 0.4, 2.0]))
        x, y = r.T_world_base[:2, 3]
        assert occ.distance(x, y) >= occ.radius_m
        assert 0.25 - 1e-9 <= x <= 5.0 - 0.25 + 1e-9 and 0.25 - 1e-9 <= y <= 4.0 - 0.25 + 1e-9
        contacts += r.contact
    assert contacts > 0  # it did hit things


def test_close_finishes_every_sink_even_when_one_fails(toy):
    """A failing sink (e.g. disk full in the MCAP writer) must not leave the others unclosed
    (unfinished files, a viewer process left running); the first error is raised after."""
    closed = []

    class Sink:
        def __init__(self, name, fail):
            self.name, self.fail = name, fail

        def open(self, info):
            pass

        def on_step(self, result):
            pass

        def close(self):
            closed.append(self.name)
            if self.fail:
                raise OSError(f"{self.name}: disk full")

    sim = Simulator(toy, default_robot(), SimConfig(cameras=()))
    for name, fail in (("a", False), ("b", True), ("c", False)):
        sim.add_sink(Sink(name, fail))
    sim.reset(0)
    with pytest.raises(OSError, match="b: disk full"):
        sim.close()
    assert closed == ["a", "b", "c"]
    sim.close()  # once only
    assert closed == ["a", "b", "c"]
