"""Synthetic step-loop output with known answers, for sink tests and the sink benchmark.

The default robot (presim_bot URDF, real forward kinematics) drives a circle of known radius while
its head pans; images are an analytic gradient (color) and a tilted plane (depth), so readers can
check every number without running the simulator.
"""

from __future__ import annotations

import numpy as np

from presim.geometry import Intrinsics, compose, make_pose, rotation_z
from presim.sim.robot import default_robot
from presim.sim.types import CameraObservation, JointStates, Odometry, SimInfo, StepResult

__all__ = ["synthetic_info", "synthetic_steps", "synthetic_color", "synthetic_depth"]


def synthetic_color(width: int, height: int, step_idx: int) -> np.ndarray:
    u = np.linspace(0, 255, width, dtype=np.float32)[None, :]
    v = np.linspace(0, 255, height, dtype=np.float32)[:, None]
    img = np.empty((height, width, 3), np.uint8)
    img[..., 0] = u.astype(np.uint8)
    img[..., 1] = v.astype(np.uint8)
    img[..., 2] = np.uint8((step_idx * 7) % 256)
    return img


def synthetic_depth(width: int, height: int, step_idx: int) -> np.ndarray:
    """Tilted plane 1..4 m, a 10x10 invalid (0) square in the top-left corner."""
    u = np.arange(width, dtype=np.float32)[None, :]
    d = np.broadcast_to(1.0 + 3.0 * u / width + 0.01 * step_idx, (height, width)).astype(np.float32)
    d = d.copy()
    d[:10, :10] = 0.0
    return d


def synthetic_info(num_points: int = 5000, num_views: int = 6, dt_s: float = 0.1, seed: int = 0) -> SimInfo:
    robot = default_robot()
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([-2, -2, 0], [2, 2, 2.5], size=(num_points, 3)).astype(np.float32)
    rgb = rng.integers(0, 255, size=(num_points, 3), dtype=np.uint8)
    K = Intrinsics.from_fov(64, 48, 60.0)
    T = np.stack([make_pose(rotation_z(a) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float),
                            [np.cos(a), np.sin(a), 1.2]) for a in np.linspace(0, 2 * np.pi, num_views, endpoint=False)])
    return SimInfo("synthetic", xyz, rgb, T, tuple([K] * num_views), robot.urdf_xml,
                   dict(robot.link_parents), dt_s)


def synthetic_steps(num_steps: int, width: int = 64, height: int = 48, dt_s: float = 0.1,
                    radius_m: float = 1.0, speed_mps: float = 0.3, camera_every: int = 1,
                    drift_m: float = 0.0):
    """Yield ``num_steps`` StepResults of the default robot driving a circle (centre (0, radius)).

    ``drift_m``: odometry x offset growing linearly to this value (map->odom then absorbs it).
    """

    robot = default_robot()
    K = Intrinsics.from_fov(width, height, 60.0)
    wz = speed_mps / radius_m
    pan = robot.joint_names.index("head_pan_joint") if "head_pan_joint" in robot.joint_names else None
    for i in range(num_steps):
        t = i * dt_s
        yaw = wz * t
        T_world_base = make_pose(rotation_z(yaw), [radius_m * np.sin(yaw), radius_m * (1 - np.cos(yaw)), 0.0])
        q = np.zeros(len(robot.joint_names))
        qd = np.zeros_like(q)
        if pan is not None:
            q[pan] = 0.5 * np.sin(t)
            qd[pan] = 0.5 * np.cos(t)
        poses = robot.fk(q)
        T_odom_base = T_world_base.copy()
        T_odom_base[0, 3] += drift_m * i / max(num_steps - 1, 1)
        cams = ()
        if i % camera_every == 0:
            T_world_cam = compose(T_world_base, robot.T_base_camera(link_poses=poses))
            cams = (CameraObservation("head_camera", robot.camera_link, t, synthetic_color(width, height, i),
                                      synthetic_depth(width, height, i), np.ones((height, width), bool), K,
                                      T_world_cam),)
        yield StepResult(
            step_idx=i, sim_time_s=t, T_world_base=T_world_base, link_poses=poses,
            joint_states=JointStates(tuple(robot.joint_names), q, qd),
            odometry=Odometry(T_odom_base, np.array([speed_mps, 0, 0, 0, 0, wz])),
            cameras=cams, applied_command=np.array([speed_mps, 0.0, wz]), contact=False,
            outside_captured_area=False)
