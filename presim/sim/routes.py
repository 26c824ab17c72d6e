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
from presim.sim.controllers import Action, KeyboardTeleop, TrajectoryReplay, WaypointFollower
from presim.sim.occupancy import plan_path
from presim.sim.simulator import Simulator

__all__ = ["Driver", "WaypointDriver", "ReplayDriver", "KeyboardDriver", "ground_route", "free_camera_route"]


class Driver:
    """One action per step; ``done`` when the controller has nothing left to do."""

    done: bool = False

    def start_pose(self, sim: Simulator) -> np.ndarray | None:
        """Pose to reset to (None = the simulator's seeded start)."""
        return None

    def action(self, sim: Simulator) -> Action:
        raise NotImplementedError

    def close(self) -> None:
        pass


class WaypointDriver(Driver):
    def __init__(self, waypoints_xy: np.ndarray, drive: str):
        self.follower = WaypointFollower(waypoints_xy, drive)

    def action(self, sim: Simulator) -> Action:
        cmd = self.follower.command(sim.x, sim.y, sim.yaw)
        self.done = self.follower.done
        return Action(twist=cmd)


class ReplayDriver(Driver):
    """Replays a TUM trajectory of camera (optical) poses -- the file a recording writes -- or of base
    poses (``frame='base'``). The free rig reproduces the poses exactly; a mobile base follows their
    floor projection (x, y, yaw) and still collides."""

    def __init__(self, replay: TrajectoryReplay, frame: str = "camera"):
        if frame not in ("camera", "base"):
            raise ValueError(f"replay frame must be 'camera' or 'base', got '{frame}'")
        self.replay, self.frame = replay, frame

    def _base(self, sim: Simulator, T: np.ndarray) -> np.ndarray:
        return compose(T, invert(sim.T_base_cam(0))) if self.frame == "camera" else T

    def start_pose(self, sim: Simulator) -> np.ndarray:
        return self._base(sim, self.replay.pose_at(0.0))

    def action(self, sim: Simulator) -> Action:
        t_next = sim.sim_time_s + sim.config.dt_s
        self.done = t_next >= self.replay.duration_s - 1e-9
        return Action(T_world_base=self._base(sim, self.replay.pose_at(t_next)))


class KeyboardDriver(Driver):
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
    """(K, 2) waypoints through ``num_goals`` seeded goals reachable from the base's position."""
    occ = sim.occupancy
    if occ is None:
        raise ValueError("ground_route needs a mobile base (the free rig has no occupancy map)")
    free = occ.free_mask(0.05)
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
    ii, jj = np.nonzero(labels == comp)
    pts = np.stack([occ.origin_xy[0] + (jj + 0.5) * occ.resolution_m,
                    occ.origin_xy[1] + (ii + 0.5) * occ.resolution_m], axis=1)
    route = []
    cur = np.array([sim.x, sim.y])
    for _ in range(num_goals):
        far = pts[np.hypot(*(pts - cur).T) >= min_leg_m]
        cand = far if len(far) else pts
        goal = cand[int(rng.integers(len(cand)))]
        path = plan_path(occ, tuple(cur), tuple(goal), clearance_m=0.05)
        if path is None:
            continue
        route.extend(path)
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
