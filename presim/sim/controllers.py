"""Controllers (thesis Fig. 4.14-4.15): base velocity limits, joint position control, waypoint
following, TUM trajectory replay and keyboard teleop. Each produces an :class:`Action` for
``Simulator.step``; the simulator applies the limits and returns the command it actually applied.
"""

from __future__ import annotations

import os
import select
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Mapping

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from presim.formats.tum import read_tum
from presim.geometry import check_rigid

__all__ = [
    "Action",
    "BaseLimits",
    "limit_base_command",
    "limit_free_twist",
    "joint_position_step",
    "WaypointConfig",
    "WaypointFollower",
    "load_waypoints",
    "TrajectoryReplay",
    "KeyboardTeleop",
    "wrap_angle",
]


@dataclass(frozen=True)
class Action:
    """What a controller asks of the robot for one step.

    ``twist``: mobile bases take (3,) [vx m/s, vy m/s, wz rad/s] in the base frame; the free camera
    rig takes (6,) [vx vy vz wx wy wz] in its body frame (a (3,) twist there means [vx, vy, wz]).
    ``joint_targets``: joint position setpoints (moved at most at each joint's velocity limit).
    ``T_world_base``: an exact pose to move to this step instead of integrating ``twist`` (trajectory
    replay); a mobile base keeps only its planar part (x, y, yaw) and still collides.
    """

    twist: np.ndarray = field(default_factory=lambda: np.zeros(3))
    joint_targets: Mapping[str, float] | None = None
    T_world_base: np.ndarray | None = None


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Angle wrapped to (-pi, pi]."""
    return np.arctan2(np.sin(a), np.cos(a))


# ---- base velocity limits ------------------------------------------------------------------------
@dataclass(frozen=True)
class BaseLimits:
    """Speed and acceleration limits of the base (defaults: a slow indoor robot)."""

    max_vx_mps: float = 0.6
    """|vx| limit, m/s."""
    max_vy_mps: float = 0.4
    """|vy| limit for holonomic bases, m/s (differential drive: vy is always 0)."""
    max_wz_radps: float = 1.2
    """|wz| limit, rad/s."""
    max_acc_mps2: float = 1.0
    """Linear acceleration limit per axis, m/s^2."""
    max_ang_acc_radps2: float = 3.0
    """Angular acceleration limit, rad/s^2."""
    max_vz_mps: float = 0.3
    """Free camera rig: |vz| limit, m/s."""
    max_w_radps: float = 1.0
    """Free camera rig: |wx|, |wy| limit, rad/s."""


def limit_base_command(cmd: np.ndarray, prev: np.ndarray, limits: BaseLimits, drive: str, dt: float) -> np.ndarray:
    """The (3,) [vx, vy, wz] a mobile base applies for ``cmd`` after the previous applied ``prev``:
    vy is clipped to 0 for differential drive, each component to its speed limit, and the change
    from ``prev`` to the acceleration limit times ``dt``."""
    cmd = np.asarray(cmd, dtype=np.float64)
    if cmd.shape != (3,) or not np.all(np.isfinite(cmd)):
        raise ValueError(f"base command must be 3 finite numbers [vx, vy, wz], got {cmd!r}")
    # On Python floats (called every step; numpy's small-array calls cost more than the arithmetic),
    # with np.clip's exact comparisons (_clip).
    vmax = (float(limits.max_vx_mps), float(limits.max_vy_mps) if drive == "holonomic" else 0.0,
            float(limits.max_wz_radps))
    amax = (float(limits.max_acc_mps2) * dt, float(limits.max_acc_mps2) * dt, float(limits.max_ang_acc_radps2) * dt)
    p = np.asarray(prev, dtype=np.float64).tolist()
    return np.array([_clip(_clip(c, -v, v), q - a, q + a) for c, v, a, q in zip(cmd.tolist(), vmax, amax, p)])


def _clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one float: ``max`` then ``min`` by the same comparisons (also for signed zeros)."""
    y = x if x > lo else lo
    return y if y < hi else hi


def limit_free_twist(cmd: np.ndarray, prev: np.ndarray, limits: BaseLimits, dt: float) -> np.ndarray:
    """(6,) [vx vy vz wx wy wz] of the free rig after speed and acceleration limits."""
    cmd = np.asarray(cmd, dtype=np.float64)
    if cmd.shape == (3,):
        cmd = np.array([cmd[0], cmd[1], 0.0, 0.0, 0.0, cmd[2]])
    if cmd.shape != (6,) or not np.all(np.isfinite(cmd)):
        raise ValueError(f"free-rig twist must be 6 finite numbers [vx vy vz wx wy wz], got {cmd!r}")
    vmax = np.array([limits.max_vx_mps, limits.max_vx_mps, limits.max_vz_mps,
                     limits.max_w_radps, limits.max_w_radps, limits.max_wz_radps])
    amax = np.array([limits.max_acc_mps2] * 3 + [limits.max_ang_acc_radps2] * 3) * dt
    return np.clip(np.clip(cmd, -vmax, vmax), prev - amax, prev + amax)


# ---- joints --------------------------------------------------------------------------------------
def joint_position_step(q: np.ndarray, target: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                        vel_limit: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Move joints ``q`` towards ``target`` (clipped to [lower, upper]) by at most ``vel_limit * dt``.
    Returns (new positions, velocities actually used)."""
    goal = np.clip(target, lower, upper)
    step = np.clip(goal - q, -vel_limit * dt, vel_limit * dt)
    q_new = q + step
    return q_new, step / dt


# ---- waypoints -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class WaypointConfig:
    """Waypoint follower gains and tolerances."""

    tolerance_m: float = 0.15
    """A waypoint counts as reached within this distance."""
    k_lin: float = 1.0
    """Linear gain, 1/s (speed = k_lin * distance, then limited by the base)."""
    k_ang: float = 2.0
    """Heading gain, 1/s."""
    turn_in_place_rad: float = 0.6
    """Differential drive turns in place while the heading error exceeds this."""


class WaypointFollower:
    """Drives a base through (N, 2) world waypoints (x, y) in order (pure pursuit of the next one)."""

    def __init__(self, waypoints_xy: np.ndarray, drive: str = "diff", config: WaypointConfig = WaypointConfig()):
        wp = np.asarray(waypoints_xy, dtype=np.float64)
        if wp.ndim != 2 or wp.shape[1] < 2 or len(wp) == 0 or not np.all(np.isfinite(wp)):
            raise ValueError(f"waypoints must be a non-empty finite (N, 2) array, got shape {wp.shape}")
        self.waypoints = wp[:, :2]
        self.drive = drive
        self.config = config
        self.idx = 0

    @property
    def done(self) -> bool:
        return self.idx >= len(self.waypoints)

    def command(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(3,) [vx, vy, wz] towards the current waypoint from base pose (x, y, yaw)."""
        while not self.done and np.hypot(*(self.waypoints[self.idx] - (x, y))) < self.config.tolerance_m:
            self.idx += 1
        if self.done:
            return np.zeros(3)
        dx, dy = self.waypoints[self.idx] - (x, y)
        dist = float(np.hypot(dx, dy))
        err = float(wrap_angle(np.arctan2(dy, dx) - yaw))
        c = self.config
        if self.drive == "holonomic":
            c_, s_ = np.cos(yaw), np.sin(yaw)
            return np.array([c.k_lin * (c_ * dx + s_ * dy), c.k_lin * (-s_ * dx + c_ * dy), c.k_ang * err])
        v = 0.0 if abs(err) > c.turn_in_place_rad else c.k_lin * dist * np.cos(err)
        return np.array([v, 0.0, c.k_ang * err])


def load_waypoints(path: str | Path) -> np.ndarray:
    """Waypoints file: one ``x y`` (metres, world frame) per line; ``#`` comments; commas allowed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: waypoints file not found")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise ValueError(f"{path}:{n}: expected 'x y' numbers, got '{line}'") from None
        if len(vals) < 2:
            raise ValueError(f"{path}:{n}: expected 'x y', got '{line}'")
        if not np.all(np.isfinite(vals[:2])):
            raise ValueError(f"{path}:{n}: non-finite waypoint '{line}'")
        rows.append(vals[:2])
    if not rows:
        raise ValueError(f"{path}: no waypoints")
    return np.array(rows)


# ---- trajectory replay ---------------------------------------------------------------------------
class TrajectoryReplay:
    """Pose at sim time ``t``: the trajectory played from its first stamp (t = 0 -> first pose),
    interpolated linearly in position and by slerp in rotation; held at the last pose at the end."""

    def __init__(self, stamps_s: np.ndarray, poses: np.ndarray):
        stamps_s = np.asarray(stamps_s, dtype=np.float64)
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(stamps_s) or len(poses) == 0:
            raise ValueError(f"need (N,) stamps and (N, 4, 4) poses, got {stamps_s.shape}, {poses.shape}")
        self.poses = np.stack([check_rigid(T, f"trajectory pose {i}") for i, T in enumerate(poses)])
        self.t = stamps_s - stamps_s[0]
        self._slerp = Slerp(self.t, Rotation.from_matrix(self.poses[:, :3, :3])) if len(poses) > 1 else None

    @classmethod
    def from_file(cls, path: str | Path) -> "TrajectoryReplay":
        """Replay of a TUM file, read strictly by :func:`presim.formats.tum.read_tum`."""
        return cls(*read_tum(path))

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])

    def pose_at(self, t_s: float) -> np.ndarray:
        if self._slerp is None or t_s <= 0:
            return self.poses[0].copy()
        if t_s >= self.t[-1]:
            return self.poses[-1].copy()
        i = int(np.searchsorted(self.t, t_s, side="right")) - 1
        i = min(i, len(self.t) - 2)
        a = (t_s - self.t[i]) / (self.t[i + 1] - self.t[i])
        if a < 1e-9:
            return self.poses[i].copy()  # exact poses at the trajectory's own stamps
        T = np.eye(4)
        T[:3, :3] = self._slerp([t_s]).as_matrix()[0]
        T[:3, 3] = (1 - a) * self.poses[i, :3, 3] + a * self.poses[i + 1, :3, 3]
        return T


# ---- keyboard ------------------------------------------------------------------------------------
_KEY_HELP = "w/s forward/back  a/d turn  q/e strafe  r/f up/down (free rig)  i/k tilt  j/l pan  space stop  x quit"


class KeyboardTeleop:
    """Non-blocking keyboard teleop from a terminal (or any readable fd: a pipe or pty in tests).

    Keys: ``w``/``s`` forward/back, ``a``/``d`` turn left/right, ``q``/``e`` strafe left/right
    (holonomic / free rig), ``r``/``f`` up/down (free rig), ``i``/``k`` head tilt down/up, ``j``/``l``
    head pan left/right, space stops, ``x`` (or ``Ctrl-C``/EOF) quits. A motion key sets the
    command for ``hold_steps`` steps (terminal key-repeat keeps it going while held).
    On a TTY the terminal is put in cbreak mode (termios) and restored by :meth:`close`.
    """

    help = _KEY_HELP

    def __init__(self, stream: IO | int | None = None, speed_mps: float = 0.4, turn_radps: float = 0.8,
                 joint_step_rad: float = 0.1, hold_steps: int = 5):
        self.fd = stream if isinstance(stream, int) else (stream or sys.stdin).fileno()
        self.speed, self.turn, self.joint_step, self.hold_steps = speed_mps, turn_radps, joint_step_rad, hold_steps
        self.twist = np.zeros(6)
        self.joint_delta: dict[str, float] = {}
        self.quit = False
        self._left = 0
        self._saved = None
        if os.isatty(self.fd):
            import termios
            import tty

            self._saved = termios.tcgetattr(self.fd)
            tty.setcbreak(self.fd)

    def close(self) -> None:
        if self._saved is not None:
            import termios

            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            self._saved = None

    def __enter__(self) -> "KeyboardTeleop":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _read_keys(self) -> str:
        keys = []
        while select.select([self.fd], [], [], 0)[0]:
            data = os.read(self.fd, 64)
            if not data:  # EOF (pipe closed)
                self.quit = True
                break
            keys.append(data.decode("utf-8", errors="ignore"))
        return "".join(keys)

    def poll(self) -> tuple[np.ndarray, dict[str, float]]:
        """Read pending keys; return (6,) twist [vx vy vz wx wy wz] and head joint increments
        (``head_pan_joint`` / ``head_tilt_joint`` deltas, radians). Sets ``quit`` on x / Ctrl-C / EOF."""
        keys = self._read_keys()
        joint_delta: dict[str, float] = {}
        v, w = self.speed, self.turn
        table = {"w": (0, v), "s": (0, -v), "q": (1, v), "e": (1, -v), "r": (2, v), "f": (2, -v),
                 "a": (5, w), "d": (5, -w)}
        for k in keys.lower():
            if k in table:
                axis, val = table[k]
                self.twist = np.zeros(6)
                self.twist[axis] = val
                self._left = self.hold_steps
            elif k == " ":
                self.twist = np.zeros(6)
                self._left = 0
            elif k in "ik":
                joint_delta["head_tilt_joint"] = joint_delta.get("head_tilt_joint", 0.0) + (self.joint_step if k == "i" else -self.joint_step)
            elif k in "jl":
                joint_delta["head_pan_joint"] = joint_delta.get("head_pan_joint", 0.0) + (self.joint_step if k == "j" else -self.joint_step)
            elif k in ("x", "\x03", "\x04"):
                self.quit = True
        out = self.twist.copy() if self._left > 0 else np.zeros(6)
        self._left = max(0, self._left - 1)
        return out, joint_delta
