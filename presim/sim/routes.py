"""Drivers: turn a controller (waypoints, TUM replay, keyboard, built-in route) into one
:class:`~presim.sim.controllers.Action` per step, and the built-in routes that make
``presim drive SCENE`` show something without any input.

- Mobile base: reachable waypoints drawn from the seed on the free occupancy cells, joined by
  shortest paths on the map (so the route never asks the base to cross a wall).
- Free camera rig: a smooth path through a seeded stretch of the captured camera poses, with a
  small seeded sideways sway (so the views are novel, not copies of the inputs).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import label

from presim.geometry import compose, invert
from presim.sim.controllers import Action, KeyboardTeleop, TrajectoryReplay, WaypointFollower, wrap_angle
from presim.sim.occupancy import plan_path
from presim.sim.simulator import Simulator

__all__ = ["Driver", "WaypointDriver", "RouteDriver", "ReplayDriver", "KeyboardDriver", "ground_route", "free_camera_route",
           "ended_early"]


class Driver:
    """One action per step; ``done`` when the controller has nothing left to do."""

    done: bool = False
    label: str = "controller"
    """What the driver follows, for messages ("built-in route", "waypoints", "trajectory")."""

    def start_pose(self, sim: Simulator) -> np.ndarray | None:
        """Pose to reset to (None = the simulator's seeded start)."""
        return None

    def start_joints(self, sim: Simulator) -> dict[str, float] | None:
        """Joint positions to reset to (None = the robot's initial ones)."""
        return None

    def action(self, sim: Simulator) -> Action:
        raise NotImplementedError

    def close(self) -> None:
        pass


class WaypointDriver(Driver):
    label = "waypoints"

    def __init__(self, waypoints_xy: np.ndarray, drive: str):
        self.follower = WaypointFollower(waypoints_xy, drive)

    def action(self, sim: Simulator) -> Action:
        cmd = self.follower.command(sim.x, sim.y, sim.yaw)
        self.done = self.follower.done
        return Action(twist=cmd)


class RouteDriver(WaypointDriver):
    """Waypoint following that also aims the head (pan/tilt joints, when the robot has them) along
    the nearest captured view, so the camera looks where the capture looked (fewer holes)."""

    label = "built-in route"

    def __init__(self, waypoints_xy: np.ndarray, sim: Simulator, pan_joint: str = "head_pan_joint",
                 tilt_joint: str = "head_tilt_joint"):
        super().__init__(waypoints_xy, sim.robot.drive)
        names = sim.robot.joint_names
        self.pan = pan_joint if pan_joint in names else None
        self.tilt = tilt_joint if tilt_joint in names else None
        fwd = sim.scene.T_world_cam[:, :3, 2]
        self.view_xy = sim.scene.camera_centres[:, :2]
        self.view_yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
        self.view_pitch = np.arcsin(np.clip(-fwd[:, 2], -1.0, 1.0))  # > 0: looking down

    def action(self, sim: Simulator) -> Action:
        act = super().action(sim)
        if self.pan is None and self.tilt is None:
            return act
        k = int(np.argmin(np.hypot(*(self.view_xy - (sim.x, sim.y)).T)))
        targets = {}
        if self.pan is not None:
            targets[self.pan] = float(wrap_angle(self.view_yaw[k] - sim.yaw))
        if self.tilt is not None:
            targets[self.tilt] = float(self.view_pitch[k])
        return Action(twist=act.twist, joint_targets=targets)


class ReplayDriver(Driver):
    """Replays a TUM trajectory of camera (optical) poses -- the file a recording writes -- or of base
    poses (``frame='base'``). The free rig reproduces the poses exactly. A mobile base follows their
    floor projection (x, y, yaw) and still collides; with camera poses and a ``head_tilt_joint`` the
    head is set to pan 0 / tilt = the camera's pitch, so a camera that stayed level in roll (any pose
    the robot itself produced) is reproduced exactly as long as the tilt keeps up with its
    velocity limit."""

    label = "trajectory"

    def __init__(self, replay: TrajectoryReplay, frame: str = "camera", pan_joint: str = "head_pan_joint",
                 tilt_joint: str = "head_tilt_joint", label: str | None = None):
        if label is not None:
            self.label = label
        if frame not in ("camera", "base"):
            raise ValueError(f"replay frame must be 'camera' or 'base', got '{frame}'")
        self.replay, self.frame = replay, frame
        self.pan_joint, self.tilt_joint = pan_joint, tilt_joint

    def _joint_targets(self, sim: Simulator, T_world_cam: np.ndarray) -> dict[str, float]:
        names = sim.robot.joint_names
        if sim.is_free or self.frame != "camera" or self.tilt_joint not in names:
            return {}
        targets = {self.tilt_joint: float(np.arcsin(np.clip(-T_world_cam[2, 2], -1.0, 1.0)))}
        if self.pan_joint in names:
            targets[self.pan_joint] = 0.0
        return targets

    def _base(self, sim: Simulator, T: np.ndarray, q: np.ndarray) -> np.ndarray:
        if self.frame == "base":
            return T
        return compose(T, invert(sim.T_base_cam(0, q)))

    def start_joints(self, sim: Simulator) -> dict[str, float]:
        return self._joint_targets(sim, self.replay.pose_at(0.0))

    def start_pose(self, sim: Simulator) -> np.ndarray:
        q = sim.initial_joints(self.start_joints(sim))
        return self._base(sim, self.replay.pose_at(0.0), q)

    def action(self, sim: Simulator) -> Action:
        t_next = sim.sim_time_s + sim.config.dt_s
        self.done = t_next >= self.replay.duration_s - 1e-9
        T = self.replay.pose_at(t_next)
        targets = self._joint_targets(sim, T)
        q_next = sim.predict_joints(targets)
        return Action(T_world_base=self._base(sim, T, q_next), joint_targets=targets or None)


def ended_early(driver: Driver, steps_done: int, steps_requested: int) -> str | None:
    """Why a drive stopped before ``steps_requested`` steps (None when it did not, or when the user
    quit the keyboard teleop)."""
    if not driver.done or steps_done >= steps_requested or isinstance(driver, KeyboardDriver):
        return None
    return f"the {driver.label} ended after {steps_done} of {steps_requested} steps"


class KeyboardDriver(Driver):
    label = "keyboard"

    def __init__(self, teleop: KeyboardTeleop):
        self.teleop = teleop

    def action(self, sim: Simulator) -> Action:
        twist, joint_delta = self.teleop.poll()
        self.done = self.teleop.quit
        targets = None
        if joint_delta:
            targets = {}
            for name, d in joint_delta.items():
                if name in sim.robot.joint_names:
                    targets[name] = float(sim.q_target[sim.robot.joint_index(name)] + d)
        return Action(twist=twist if sim.is_free else twist[[0, 1, 5]], joint_targets=targets)

    def close(self) -> None:
        self.teleop.close()


def ground_route(sim: Simulator, rng: np.random.Generator, num_goals: int = 4,
                 min_leg_m: float = 1.0) -> np.ndarray:
    """(K, 2) waypoints through ``num_goals`` seeded goals reachable from the base's position, drawn
    among known free cells within 0.5 m of where a captured camera stood (any known free cell when
    there are too few), joined by shortest paths on the occupancy map."""
    occ = sim.occupancy
    if occ is None:
        raise ValueError("ground_route needs a mobile base (the free rig has no occupancy map)")
    # Components of the cells the base fits in (crossing unknown floor is allowed); goals are
    # drawn only among known ones.
    free = occ.free_mask(0.05, include_unknown=True)
    labels, _ = label(free, structure=np.ones((3, 3)))
    i, j = occ.cell_of(sim.x, sim.y)
    inside = 0 <= i < free.shape[0] and 0 <= j < free.shape[1]
    comp = labels[i, j] if inside else 0
    if comp == 0:  # start cell not free (e.g. hugging a wall): use the nearest free component
        ii, jj = np.nonzero(free)
        if len(ii) == 0:
            return np.array([[sim.x, sim.y]])
        k = int(np.argmin((ii - i) ** 2 + (jj - j) ** 2))
        comp = labels[ii[k], jj[k]]
    mask = (labels == comp) & occ.known
    # Goals near where the capture's cameras stood: the robot then sees what was captured.
    seeds = np.zeros_like(mask)
    for x, y in sim.scene.camera_centres[:, :2]:
        i, j = occ.cell_of(x, y)
        if 0 <= i < mask.shape[0] and 0 <= j < mask.shape[1]:
            seeds[i, j] = True
    if seeds.any():
        from scipy.ndimage import distance_transform_edt

        near = mask & (distance_transform_edt(~seeds) * occ.resolution_m <= 0.5)
        if near.sum() >= num_goals:
            mask = near
    ii, jj = np.nonzero(mask)
    if len(ii) == 0:
        return np.array([[sim.x, sim.y]])
    pts = np.stack([occ.origin_xy[0] + (jj + 0.5) * occ.resolution_m,
                    occ.origin_xy[1] + (ii + 0.5) * occ.resolution_m], axis=1)
    route = []
    cur = np.array([sim.x, sim.y])
    heading = sim.yaw
    for _ in range(num_goals):
        far = pts[np.hypot(*(pts - cur).T) >= min_leg_m]
        cand = far if len(far) else pts
        # Prefer goals roughly ahead, so the route starts by driving, not by turning around.
        ahead = cand[np.abs(wrap_angle(np.arctan2(*(cand - cur).T[::-1]) - heading)) < np.pi / 3]
        if len(ahead):
            cand = ahead
        goal = cand[int(rng.integers(len(cand)))]
        path = plan_path(occ, tuple(cur), tuple(goal), clearance_m=0.05)
        if path is None:
            continue
        route.extend(path)
        heading = float(np.arctan2(*(path[-1] - (path[-2] if len(path) > 1 else cur))[::-1]))
        cur = path[-1]
    return np.array(route) if route else np.array([[sim.x, sim.y]])


def free_camera_route(sim: Simulator, rng: np.random.Generator, num_steps: int,
                      sway_m: float = 0.02, max_views: int = 20) -> TrajectoryReplay:
    """A smooth camera path for ``num_steps`` steps through a seeded stretch of the captured poses."""
    scene = sim.scene
    n = len(scene)
    m = min(n, max_views)
    s = int(rng.integers(0, n - m + 1))
    idx = np.arange(s, s + m)
    if rng.random() < 0.5:
        idx = idx[::-1]
    poses = scene.T_world_cam[idx].copy()
    # Smooth the positions (moving average over 3) so capture jitter does not shake the camera.
    if m >= 3:
        c = poses[:, :3, 3]
        pad = np.concatenate([c[:1], c, c[-1:]])
        poses[:, :3, 3] = (pad[:-2] + pad[1:-1] + pad[2:]) / 3.0
    duration = max(num_steps * sim.config.dt_s, sim.config.dt_s)
    stamps = np.linspace(0.0, duration, m) if m > 1 else np.array([0.0])
    # Sideways sway along each camera's x axis (one seeded sine period over the path).
    phase = rng.uniform(0, 2 * np.pi)
    sway = sway_m * np.sin(2 * np.pi * np.linspace(0, 1, m) + phase)
    poses[:, :3, 3] += poses[:, :3, 0] * sway[:, None]
    return TrajectoryReplay(stamps, poses)
