"""Controllers: limits, joint position control, waypoints, TUM replay, keyboard teleop (known answers)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from presim.formats.tum import read_tum
from presim.geometry import look_at, pose_to_tum
from presim.sensors.odometry import integrate_planar
from presim.sim.controllers import (BaseLimits, KeyboardTeleop, TrajectoryReplay, WaypointFollower,
                                    joint_position_step, limit_base_command, limit_free_twist,
                                    load_waypoints)

LIM = BaseLimits(max_vx_mps=0.5, max_vy_mps=0.3, max_wz_radps=1.0, max_acc_mps2=1.0, max_ang_acc_radps2=2.0)


def test_speed_limits_clip_and_vy_for_diff_drive():
    prev = np.array([0.5, 0.0, 1.0])
    out = limit_base_command(np.array([2.0, 0.7, 3.0]), prev, LIM, "diff", dt=0.1)
    assert np.allclose(out, [0.5, 0.0, 1.0])  # vy clipped to 0 for differential drive
    out = limit_base_command(np.array([2.0, 0.7, -3.0]), np.array([0.5, 0.3, -1.0]), LIM, "holonomic", 0.1)
    assert np.allclose(out, [0.5, 0.3, -1.0])


def test_acceleration_limits():
    out = limit_base_command(np.array([0.5, 0.0, 1.0]), np.zeros(3), LIM, "diff", dt=0.1)
    assert np.allclose(out, [0.1, 0.0, 0.2])  # 1 m/s^2 and 2 rad/s^2 over 0.1 s
    out = limit_free_twist(np.array([0.5, 0, 0.3, 0, 0, 1.0]), np.zeros(6), LIM, dt=0.1)
    assert np.allclose(out, [0.1, 0, 0.1, 0, 0, 0.2])
    with pytest.raises(ValueError, match="3 finite"):
        limit_base_command(np.array([np.nan, 0, 0]), np.zeros(3), LIM, "diff", 0.1)


def test_base_command_limits_equal_numpy_clip_bit_for_bit():
    """limit_base_command (on Python floats) = the two np.clip calls it replaces, bit for bit,
    signed zeros included, for both drives and commands inside, outside and at the limits."""
    rng = np.random.default_rng(5)
    cmds = np.concatenate([rng.uniform(-3, 3, (300, 3)), np.zeros((5, 3)), -np.zeros((5, 3)),
                           np.array([[0.5, 0.3, 1.0], [-0.5, -0.3, -1.0], [0.0, -0.2, 0.0]])])
    for drive in ("diff", "holonomic"):
        for cmd in cmds:
            prev = rng.uniform(-1, 1, 3) * rng.integers(0, 2, 3)
            dt = float(rng.choice([0.1, 0.05, 1.0 / 30.0]))
            vmax = np.array([LIM.max_vx_mps, LIM.max_vy_mps if drive == "holonomic" else 0.0, LIM.max_wz_radps])
            amax = np.array([LIM.max_acc_mps2, LIM.max_acc_mps2, LIM.max_ang_acc_radps2]) * dt
            want = np.clip(np.clip(cmd, -vmax, vmax), prev - amax, prev + amax)
            got = limit_base_command(cmd, prev, LIM, drive, dt)
            assert got.dtype == np.float64 and got.shape == (3,)
            np.testing.assert_array_equal(got, want)
            assert (np.signbit(got) == np.signbit(want)).all(), (cmd, prev, got, want)


def test_integrate_planar_straight_and_arc():
    assert np.allclose(integrate_planar(0, 0, 0, 0.5, 0, 0, 2.0), (1.0, 0.0, 0.0))
    # Arc: v = 0.5 m/s, w = 0.5 rad/s for pi s: a quarter circle of radius r = v / w = 1,
    # x = r sin(w t), y = r (1 - cos(w t)) with w t = pi/2.
    x, y, yaw = integrate_planar(0, 0, 0, 0.5, 0, 0.5, np.pi)
    assert np.allclose([x, y, yaw], [1.0, 1.0, np.pi / 2], atol=1e-12)
    # Many small steps agree with one exact step.
    s = (0.0, 0.0, 0.0)
    for _ in range(1000):
        s = integrate_planar(*s, 0.5, 0.0, 0.5, np.pi / 1000)
    assert np.allclose(s, (1.0, 1.0, np.pi / 2), atol=1e-9)


def test_joint_position_control_respects_velocity_limits():
    q = np.zeros(2)
    lo, hi, vmax = np.array([-2.0, -0.6]), np.array([2.0, 0.9]), np.array([1.5, 1.0])
    target = np.array([1.0, 5.0])  # second beyond its limit: goes to 0.9
    traj = [q]
    for _ in range(20):
        q, qd = joint_position_step(q, target, lo, hi, vmax, dt=0.1)
        assert np.all(np.abs(qd) <= vmax + 1e-12)
        traj.append(q)
    traj = np.array(traj)
    assert np.all(np.abs(np.diff(traj, axis=0)) <= vmax * 0.1 + 1e-12)
    assert np.allclose(traj[-1], [1.0, 0.9])
    assert np.allclose(traj[1], [0.15, 0.1])


def test_waypoint_follower_reaches_waypoints_kinematically():
    wps = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.5]])
    for drive in ("diff", "holonomic"):
        f = WaypointFollower(wps, drive)
        x = y = yaw = 0.0
        prev = np.zeros(3)
        reached = []
        for _ in range(600):
            cmd = limit_base_command(f.command(x, y, yaw), prev, LIM, drive, 0.05)
            prev = cmd
            x, y, yaw = integrate_planar(x, y, yaw, *cmd, 0.05)
            reached.append(f.idx)
            if f.done:
                break
        assert f.done, drive
        assert np.hypot(x - 0.0, y - 1.5) < f.config.tolerance_m + 0.05


def test_tum_trajectory_replay_reproduces_poses(tmp_path):
    poses = np.stack([look_at([0.1 * k, 0.05 * k, 1.0], [0.1 * k + 1.0, 0.0, 0.8]) for k in range(6)])
    stamps = 100.0 + 0.2 * np.arange(6)
    p = tmp_path / "traj.txt"
    p.write_text("# stamp x y z qx qy qz qw\n" + "\n".join(
        f"{s:.6f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(T)) for s, T in zip(stamps, poses)))
    s2, P2 = read_tum(p)
    assert np.allclose(s2, stamps) and np.allclose(P2, poses, atol=1e-7)
    rep = TrajectoryReplay.from_file(p)
    for k in range(6):
        assert np.allclose(rep.pose_at(0.2 * k), poses[k], atol=1e-7)
    mid = rep.pose_at(0.1)
    assert np.allclose(mid[:3, 3], (poses[0, :3, 3] + poses[1, :3, 3]) / 2, atol=1e-7)
    assert np.allclose(rep.pose_at(99.0), poses[-1], atol=1e-7)


def test_load_waypoints(tmp_path):
    p = tmp_path / "wp.txt"
    p.write_text("# x y\n1 2\n3, 4  # comment\n")
    assert np.allclose(load_waypoints(p), [[1, 2], [3, 4]])
    p.write_text("1 a\n")
    with pytest.raises(ValueError, match="wp.txt:1"):
        load_waypoints(p)
    p.write_text("1 2\nnan 4\n")
    with pytest.raises(ValueError, match="wp.txt:2: non-finite waypoint"):
        load_waypoints(p)


def test_keyboard_teleop_through_a_pipe():
    r, w = os.pipe()
    try:
        tele = KeyboardTeleop(r, speed_mps=0.4, turn_radps=0.8, hold_steps=2)
        twist, joints = tele.poll()
        assert np.allclose(twist, 0) and not joints and not tele.quit  # nothing typed: no block, no motion
        os.write(w, b"w")
        assert np.allclose(tele.poll()[0], [0.4, 0, 0, 0, 0, 0])
        assert np.allclose(tele.poll()[0], [0.4, 0, 0, 0, 0, 0])  # held for hold_steps
        assert np.allclose(tele.poll()[0], 0)  # then released
        os.write(w, b"a")
        assert np.allclose(tele.poll()[0], [0, 0, 0, 0, 0, 0.8])
        os.write(w, b" ik")
        twist, joints = tele.poll()
        assert np.allclose(twist, 0) and joints == {"head_tilt_joint": pytest.approx(0.0)}
        os.write(w, b"jjx")
        twist, joints = tele.poll()
        assert joints["head_pan_joint"] == pytest.approx(0.2) and tele.quit
    finally:
        os.close(r)
        os.close(w)


def test_keyboard_teleop_through_a_pty():
    import pty

    master, slave = pty.openpty()
    try:
        tele = KeyboardTeleop(slave)  # a TTY: switched to cbreak mode, restored on close
        assert tele._saved is not None
        os.write(master, b"d")
        assert np.allclose(tele.poll()[0][5], -tele.turn)
        tele.close()
        assert tele._saved is None
    finally:
        os.close(master)
        os.close(slave)
