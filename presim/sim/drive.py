"""The drive loop of ``presim drive``: pick a driver, reset, step until done, and the statistics.

:func:`run_drive` builds the :class:`~presim.sim.simulator.Simulator`, turns a
:class:`ControllerSpec` into a driver (a built-in route drawn from the seed when none is given),
attaches the sinks (recorders and viewers are passed in; this layer never imports them), runs the
steps, closes everything in ``finally`` and returns :class:`DriveStats`. The command line only
parses arguments and prints the stats.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Callable, Sequence

import numpy as np

from presim.capture.scene import Scene
from presim.io_utils import progress
from presim.sim.controllers import KeyboardTeleop, TrajectoryReplay, load_waypoints
from presim.sim.robot import Robot
from presim.sim.routes import (Driver, KeyboardDriver, ReplayDriver, RouteDriver, WaypointDriver, ended_early,
                               free_camera_route, ground_route)
from presim.sim.simulator import SimConfig, Simulator
from presim.sim.types import Sink

__all__ = ["CONTROLLER_KINDS", "ControllerSpec", "DriveConfig", "DriveStats", "make_driver", "run_drive"]

CONTROLLER_KINDS = ("route", "waypoints", "trajectory", "keyboard")


@dataclass(frozen=True)
class ControllerSpec:
    """What drives the robot."""

    kind: str = "route"
    """``route`` (built-in, drawn from the seed), ``waypoints`` (file of ``x y``, mobile base),
    ``trajectory`` (TUM file of camera poses to replay) or ``keyboard`` (teleop)."""
    path: Path | None = None
    """The waypoints / trajectory file."""
    keyboard_stream: IO | int | None = None
    """Keyboard: the terminal (or pipe) to read keys from; None = stdin."""


@dataclass(frozen=True)
class DriveConfig:
    """How long and how fast to drive."""

    steps: int = 200
    """Number of steps (fewer when the driver finishes first)."""
    seed: int = 0
    """Seed of the start pose, the built-in route and the simulator's noise."""
    realtime: bool = False
    """Pace steps to wall time (``dt`` of sim time per wall second)."""
    until_done: bool = False
    """Ignore ``steps`` and run until the driver is done (keyboard: until ``x``)."""


@dataclass(frozen=True)
class DriveStats:
    """What a drive did."""

    scene_name: str
    steps: int
    sim_time_s: float
    distance_m: float
    """Path length of the base origin."""
    contacts: int
    """Steps with a collision."""
    outside_captured_area: int
    """Steps with the camera outside the captured area."""
    images: int
    """Camera images produced."""
    T_world_base: np.ndarray
    """Final base pose (4, 4)."""
    yaw_rad: float
    """Final base yaw."""
    wall_s: float
    """Wall time of the step loop."""
    setup_s: float
    """Wall time before the first step (simulator, driver, sinks, reset, route)."""
    stage_ms_per_step: dict[str, float] = field(default_factory=dict)
    """Mean wall milliseconds per step of each simulator stage (``total`` included)."""
    ended_early: str | None = None
    """Why the drive stopped before ``DriveConfig.steps`` (the driver finished), else None."""

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.wall_s if self.wall_s > 0 else float("inf")


def make_driver(sim: Simulator, spec: ControllerSpec) -> Driver | None:
    """The driver of ``spec`` for ``sim``; None for the built-in route (drawn at reset)."""
    if spec.kind not in CONTROLLER_KINDS:
        raise ValueError(f"unknown controller {spec.kind!r}; choose one of {', '.join(CONTROLLER_KINDS)}")
    if spec.kind in ("waypoints", "trajectory") and spec.path is None:
        raise ValueError(f"controller {spec.kind} needs a file")
    if spec.kind == "waypoints":
        if sim.is_free:
            raise ValueError("--waypoints drive a mobile base; the free camera rig takes --trajectory")
        return WaypointDriver(load_waypoints(spec.path), sim.robot.drive)
    if spec.kind == "trajectory":
        return ReplayDriver(TrajectoryReplay.from_file(spec.path))
    if spec.kind == "keyboard":
        return KeyboardDriver(KeyboardTeleop(spec.keyboard_stream))
    return None


def run_drive(scene: Scene, robot: Robot, sim_config: SimConfig, controller: ControllerSpec = ControllerSpec(),
              config: DriveConfig = DriveConfig(),
              make_sinks: Callable[[], Sequence[Sink]] | None = None) -> DriveStats:
    """Drive ``robot`` through ``scene`` and return the statistics.

    ``make_sinks`` is called once the driver exists (so a bad controller file creates no
    recording); its sinks are opened at reset and closed, with the driver, when the loop ends,
    also on Ctrl-C.
    """
    if config.steps <= 0 and not config.until_done:
        raise ValueError(f"steps must be positive, got {config.steps}")
    t_setup = time.perf_counter()
    sim = Simulator(scene, robot, sim_config)
    driver = make_driver(sim, controller)
    for s in (make_sinks() if make_sinks is not None else ()):
        sim.add_sink(s)
    rng = np.random.default_rng(config.seed)
    start = driver.start_pose(sim) if driver is not None else None
    joints = driver.start_joints(sim) if driver is not None else None
    result = sim.reset(config.seed, start=start, joint_positions=joints)
    if driver is None:  # built-in route drawn from the seed
        if sim.is_free:
            driver = ReplayDriver(free_camera_route(sim, rng, config.steps), label="built-in route")
            result = sim.reset(config.seed, start=driver.start_pose(sim))
        else:
            driver = RouteDriver(ground_route(sim, rng), sim)
    setup_s = time.perf_counter() - t_setup
    dt = sim_config.dt_s
    steps = contacts = outside = images = 0
    dist = 0.0
    stage_ms: dict[str, float] = {}
    prev = result.T_world_base[:3, 3].copy()
    t0 = time.perf_counter()
    # keyboard teleop (until_done) owns the terminal: no bar there
    bar = progress(total=config.steps, desc="drive", unit="step", disable=True if config.until_done else None)
    try:
        while steps < config.steps or config.until_done:
            if driver.done:
                break
            result = sim.step(driver.action(sim))
            steps += 1
            bar.update(1)
            contacts += result.contact
            outside += result.outside_captured_area
            images += len(result.cameras)
            p = result.T_world_base[:3, 3]
            dist += float(np.linalg.norm(p - prev))
            prev = p.copy()
            for k, v in result.timings_ms.items():
                stage_ms[k] = stage_ms.get(k, 0.0) + v
            if config.realtime:
                lag = t0 + steps * dt - time.perf_counter()
                if lag > 0:
                    time.sleep(lag)
    finally:
        bar.close()
        driver.close()
        sim.close()
    wall = time.perf_counter() - t0
    return DriveStats(
        scene_name=sim.scene_name, steps=steps, sim_time_s=sim.sim_time_s, distance_m=dist, contacts=contacts,
        outside_captured_area=outside, images=images, T_world_base=result.T_world_base.copy(), yaw_rad=float(sim.yaw),
        wall_s=wall, setup_s=setup_s, stage_ms_per_step={k: v / max(steps, 1) for k, v in stage_ms.items()},
        ended_early=None if config.until_done else ended_early(driver, steps, config.steps))
