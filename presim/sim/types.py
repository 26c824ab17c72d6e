"""Types that cross the border between the simulator's step loop and its sinks
(recorder, viewer, ROS bridge). The loop calls every sink the same way and never branches on kind.
"""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass, field
from typing import Iterable, Protocol

import numpy as np

from presim.geometry import Intrinsics

__all__ = ["CameraObservation", "JointStates", "Odometry", "StepResult", "Sink", "SimInfo", "deliver"]


@dataclass(frozen=True)
class CameraObservation:
    """One RGB-D camera reading."""

    sensor_name: str
    """Sensor name from the robot config, e.g. ``head_camera``."""
    frame_id: str
    """URDF link the optical frame belongs to (OpenCV optical frame, REP-103 ``*_optical_frame``)."""
    stamp_s: float
    """Sim time of the reading, seconds."""
    color: np.ndarray
    """uint8 (H, W, 3) RGB."""
    depth_m: np.ndarray
    """float32 (H, W) metres, 0 = invalid."""
    valid: np.ndarray
    """bool (H, W): synthesized from captured views (False = filled hole)."""
    K: Intrinsics
    T_world_cam: np.ndarray
    """Exact 4x4 camera(optical)-to-world pose of the reading."""


@dataclass(frozen=True)
class JointStates:
    names: tuple[str, ...]
    position: np.ndarray
    """(J,) radians or metres."""
    velocity: np.ndarray
    """(J,) per second."""


@dataclass(frozen=True)
class Odometry:
    """Odometry estimate (may drift) and the twist actually applied."""

    T_odom_base: np.ndarray
    """4x4 base pose in the odom frame (== ground truth when drift is off)."""
    twist_base: np.ndarray
    """(6,) [vx vy vz wx wy wz] in the base frame, m/s and rad/s."""


@dataclass(frozen=True)
class StepResult:
    """Everything one step produced. Ground truth is exact; ``odometry`` may carry drift."""

    step_idx: int
    sim_time_s: float
    T_world_base: np.ndarray
    """Exact 4x4 base-to-world pose ('map' frame in ROS terms)."""
    link_poses: dict[str, np.ndarray]
    """Exact 4x4 ``T_base_link`` of every URDF link (for tf trees and viewers)."""
    joint_states: JointStates
    odometry: Odometry
    cameras: tuple[CameraObservation, ...]
    """Readings taken this step (empty when no sensor was due at its rate)."""
    applied_command: np.ndarray
    """(3,) [vx, vy, wz] after speed/acceleration limits (the command actually applied)."""
    contact: bool
    """True when the base hit an obstacle this step (motion stopped or slid)."""
    outside_captured_area: bool
    """True when the base left the region covered by the capture (the camera may see holes)."""
    timings_ms: dict[str, float] = field(default_factory=dict)
    """Wall time per stage of this step (control, collision, render, sinks ...)."""


@dataclass(frozen=True)
class SimInfo:
    """Static facts a sink may want once at start (scene cloud, input views, robot description)."""

    scene_name: str
    points_xyz: np.ndarray
    """float32 (M, 3) scene point cloud, world frame."""
    points_rgb: np.ndarray
    """uint8 (M, 3)."""
    input_T_world_cam: np.ndarray
    """(N, 4, 4) poses of the captured views."""
    input_intrinsics: tuple[Intrinsics, ...]
    urdf_xml: str
    """The robot's URDF (robot_description)."""
    link_parents: dict[str, str]
    """child link -> parent link, for the tf tree."""
    dt_s: float
    floor_z_m: float | None = None
    """Floor height at the world origin (None: the scene has no floor, e.g. a tabletop capture)."""


class Sink(Protocol):
    """Consumes the step loop's output. ``on_step`` must return quickly (queue and drop-oldest if slow)."""

    def open(self, info: SimInfo) -> None: ...

    def on_step(self, result: StepResult) -> None: ...

    def close(self) -> None: ...


def deliver(sinks: Iterable[Sink], result: StepResult) -> None:
    """Hand one step to every sink, all of them or none when the run is interrupted: a SIGINT (or a
    SIGTERM, which ``presim`` commands turn into the same interrupt) that comes while the step is
    handed over reaches its Python handler only after the last sink got the step, so the recordings
    a Ctrl-C stops (MCAP, capture folder, rerun file) hold the same steps. Only signals with a
    Python handler are held back, and only in the main thread (elsewhere the sinks are just called
    in order)."""
    sinks = list(sinks)
    if not sinks:  # nothing to hand over (an environment without recorders)
        return
    held = []
    if threading.current_thread() is threading.main_thread():
        held = [(sig, h) for sig in (signal.SIGINT, signal.SIGTERM)
                if callable(h := signal.getsignal(sig))]
    if not held:
        for s in sinks:
            s.on_step(result)
        return
    caught: list[int] = []
    for sig, _ in held:
        signal.signal(sig, lambda signum, frame: caught.append(signum))
    try:
        for s in sinks:
            s.on_step(result)
    finally:
        for sig, h in held:
            signal.signal(sig, h)
    for signum in caught[:1]:  # the first one, as it would have been handled
        dict(held)[signum](signum, None)
