"""Commands in: validation and the inbox between ROS callbacks and the step loop.

Every command a client sends is checked here before the simulator sees it (pure functions, no
rospy). An invalid command is **dropped**: the robot keeps its last valid command (a ``/cmd_vel``
then still times out after ``cmd_timeout_s`` and the base stops), the drop is counted per topic
and the reason kept for ``/diagnostics`` and the throttled ``/rosout`` warning. Invalid means:

- ``/cmd_vel``: a non-finite number (NaN, inf) or a component beyond ``±max_abs_twist``
  (sane speeds above the robot's limits are clipped by the simulator, not dropped);
- ``/joint_command``: ``name[]`` and ``position[]`` of different lengths, no joint, more than
  ``max_joints`` entries, a joint named twice, a name that is not a movable joint of the robot, a
  non-finite position, or a position outside the joint's URDF limits;
- ``/initialpose``, ``/presim/teleport``: a non-finite number, a quaternion whose norm is not 1
  (± ``quat_norm_tol``), a position beyond ``max_abs_position_m``, a frame other than ``map``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np
from presim.geometry import make_pose, quat_xyzw_to_R

__all__ = ["CommandLimits", "check_twist", "check_joint_command", "check_pose", "CommandInbox"]


@dataclass(frozen=True)
class CommandLimits:
    """What the node accepts (see the module docstring)."""

    max_abs_twist: float = 100.0
    """Largest |component| of a /cmd_vel twist, m/s or rad/s; larger ones are dropped."""
    max_joints: int = 256
    """Most entries in one /joint_command."""
    joint_tol: float = 1e-6
    """Slack on the URDF joint limits, radians or metres."""
    quat_norm_tol: float = 1e-2
    """|‖q‖ - 1| accepted for pose quaternions."""
    max_abs_position_m: float = 1e4
    """Largest |coordinate| of a teleport pose."""


def _short(s: object, n: int = 60) -> str:
    r = repr(s)
    return r if len(r) <= n else r[:n - 3] + "..."


def check_twist(values, limits: CommandLimits = CommandLimits()) -> tuple[np.ndarray | None, str | None]:
    """``(twist6, None)`` for a valid ``[vx vy vz wx wy wz]``, else ``(None, reason)``."""
    try:
        tw = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None, "twist is not 6 numbers"
    if tw.shape != (6,):
        return None, f"twist has {tw.size} numbers, expected 6"
    if not np.all(np.isfinite(tw)):
        return None, "non-finite twist component (NaN or inf)"
    if np.any(np.abs(tw) > limits.max_abs_twist):
        return None, f"twist component {float(np.abs(tw).max()):.3g} beyond ±{limits.max_abs_twist:g}"
    return tw, None


def check_joint_command(names, positions, joint_limits: dict[str, tuple[float, float]] | None,
                        limits: CommandLimits = CommandLimits()) -> tuple[dict[str, float] | None, str | None]:
    """``({name: position}, None)`` for a valid command, else ``(None, reason)``.

    ``joint_limits``: the robot's movable joints and their ``(lower, upper)`` limits (None: any
    name and value accepted, only finiteness and lengths are checked)."""
    names, positions = list(names), list(positions)
    if len(names) != len(positions):
        return None, f"name[] has {len(names)} entries but position[] has {len(positions)}"
    if not names:
        return None, "no joint named"
    if len(names) > limits.max_joints:
        return None, f"{len(names)} joints in one command (at most {limits.max_joints})"
    out: dict[str, float] = {}
    for n, p in zip(names, positions):
        if not isinstance(n, str):
            return None, f"joint name {_short(n)} is not a string"
        if n in out:
            return None, f"joint {_short(n)} named twice"
        if joint_limits is not None and n not in joint_limits:
            known = ", ".join(sorted(joint_limits)) or "none"
            return None, f"unknown or fixed joint {_short(n)} (movable joints: {known})"
        try:
            v = float(p)
        except (TypeError, ValueError):
            return None, f"position of {_short(n)} is not a number"
        if not math.isfinite(v):
            return None, f"non-finite position for joint {_short(n)} (NaN or inf)"
        if joint_limits is not None:
            lo, hi = joint_limits[n]
            if not lo - limits.joint_tol <= v <= hi + limits.joint_tol:
                return None, f"position {v:.4g} of joint {_short(n)} outside its limits [{lo:.4g}, {hi:.4g}]"
        out[n] = v
    return out, None


def check_pose(position, quat_xyzw, frame_id: str, expected_frame: str = "map",
               limits: CommandLimits = CommandLimits()) -> tuple[np.ndarray | None, str | None]:
    """``(T_world_pose 4x4, None)`` for a valid pose in ``expected_frame`` ('' accepted), else ``(None, reason)``."""

    if frame_id not in ("", expected_frame):
        return None, f"pose must be in '{expected_frame}', got frame {_short(frame_id)}"
    p = np.asarray(position, dtype=np.float64).reshape(3)
    q = np.asarray(quat_xyzw, dtype=np.float64).reshape(4)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return None, "non-finite pose (NaN or inf)"
    if np.any(np.abs(p) > limits.max_abs_position_m):
        return None, f"position {float(np.abs(p).max()):.3g} m beyond ±{limits.max_abs_position_m:g} m"
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > limits.quat_norm_tol:
        return None, f"quaternion norm {norm:.4g} is not 1"
    return make_pose(quat_xyzw_to_R(q / norm), p), None


class CommandInbox:
    """Latest valid commands from ROS callbacks (any thread), read by the step loop. Constant memory.

    ``joint_limits``: the robot's movable joints ``{name: (lower, upper)}``; None accepts any name."""

    TOPICS = ("cmd_vel", "joint_command", "initialpose", "teleport")

    def __init__(self, joint_limits: dict[str, tuple[float, float]] | None = None,
                 limits: CommandLimits = CommandLimits()):
        self._lock = threading.Lock()
        self.joint_limits = joint_limits
        self.limits = limits
        self.twist = np.zeros(6)
        self.twist_wall_s = -np.inf
        self.joint_targets: dict[str, float] = {}
        self.cmd_count = 0
        self.counters = {f"{t}_{k}": 0 for t in self.TOPICS for k in ("accepted", "dropped")}
        self.last_drop = ""
        self._drops_reported = 0
        self._requests: list[tuple[str, object, threading.Event, list]] = []
        self._teleport: np.ndarray | None = None

    # ---- writers (ROS threads) -----------------------------------------------------------------
    def count(self, topic: str, reason: str | None) -> str | None:
        """Count one ``topic`` message as accepted (``reason`` None) or dropped; returns ``reason``."""
        with self._lock:
            self.counters[f"{topic}_{'dropped' if reason else 'accepted'}"] += 1
            if reason:
                self.last_drop = f"/{topic}: {reason}"
        return reason

    def set_twist(self, twist6, received_s: float | None = None) -> str | None:
        """Store a /cmd_vel twist; returns None, or the reason it was dropped. ``received_s``: when
        it arrived (``time.monotonic()`` clock; None = now), the start of its ``cmd_timeout_s``."""
        tw, reason = check_twist(twist6, self.limits)
        if tw is not None:
            with self._lock:
                self.twist = tw.copy()
                self.twist_wall_s = time.monotonic() if received_s is None else float(received_s)
                self.cmd_count += 1
        return self.count("cmd_vel", reason)

    def set_joint_command(self, names, positions) -> str | None:
        """Store /joint_command targets; returns None, or the reason the message was dropped."""
        targets, reason = check_joint_command(names, positions, self.joint_limits, self.limits)
        if targets is not None:
            with self._lock:
                self.joint_targets.update(targets)
        return self.count("joint_command", reason)

    def set_teleport(self, T_world_base: np.ndarray) -> None:
        """Store a fire-and-forget teleport (/initialpose); only the latest one is kept."""
        with self._lock:
            self._teleport = np.array(T_world_base, dtype=np.float64)

    def take_teleport(self) -> np.ndarray | None:
        with self._lock:
            T, self._teleport = self._teleport, None
        return T

    # ---- readers (step loop) -------------------------------------------------------------------
    def current(self, timeout_s: float) -> tuple[np.ndarray, dict[str, float]]:
        with self._lock:
            fresh = time.monotonic() - self.twist_wall_s <= timeout_s
            tw = self.twist.copy() if fresh else np.zeros(6)
            jt, self.joint_targets = self.joint_targets, {}
        return tw, jt

    def stats(self) -> tuple[dict[str, int], str, bool]:
        """``(counters, last drop reason, whether anything was dropped since the previous call)``."""
        with self._lock:
            dropped = sum(v for k, v in self.counters.items() if k.endswith("_dropped"))
            new = dropped > self._drops_reported
            self._drops_reported = dropped
            return dict(self.counters), self.last_drop, new

    # ---- requests (services) -------------------------------------------------------------------
    def request(self, kind: str, arg: object, timeout_s: float = 10.0) -> object:
        """Ask the loop to do ``kind`` (reset / teleport) and wait for its answer."""
        ev, box = threading.Event(), []
        with self._lock:
            if len(self._requests) >= 8:  # bounded: refuse a request storm instead of queueing it
                raise RuntimeError("too many pending requests")
            self._requests.append((kind, arg, ev, box))
        if not ev.wait(timeout_s):
            raise TimeoutError(f"{kind}: the simulation loop did not answer in {timeout_s} s")
        if box and isinstance(box[0], BaseException):
            raise box[0]
        return box[0] if box else None

    def take_requests(self) -> list[tuple[str, object, threading.Event, list]]:
        with self._lock:
            reqs, self._requests = self._requests, []
        return reqs
