"""``presim drive``: drive a robot through a scene and watch / record what its RGB-D camera sees."""

from __future__ import annotations

import argparse
import inspect
import shutil
import sys
import time
from pathlib import Path

import numpy as np


def register(sub) -> None:
    p = sub.add_parser(
        "drive",
        help="drive a robot (URDF) through a scene: keyboard, waypoints, TUM replay or a built-in route",
        description=(
            "Drive a robot through SCENE (a saved scene folder, or a capture folder that `presim import` "
            "reads). Without a controller it follows a built-in route drawn from --seed: reachable "
            "waypoints on the free floor for a mobile base, a smooth path near the captured camera poses "
            "for the free camera rig (used automatically for scenes without a floor)."
        ),
    )
    p.add_argument("scene", type=Path, help="saved scene folder (or a capture folder to import on the fly)")
    p.add_argument("--robot", default=None,
                   help="URDF file, 'default' (presim_bot) or 'free' (free-flying camera rig); "
                        "default: presim_bot, or the free rig when the scene has no floor")
    p.add_argument("--camera-link", default=None,
                   help="URDF link of the camera (OpenCV optical frame; default camera_optical_frame)")
    p.add_argument("--camera-link-body", action="store_true",
                   help="the --camera-link is a ROS body frame (x forward, z up), not an optical frame")
    p.add_argument("--drive", choices=["diff", "holonomic"], default="diff",
                   help="base motion model (diff: vy is clipped to 0)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--controller", nargs="+", default=None, metavar="KIND [FILE]",
                   help="keyboard: teleop in this terminal; route: built-in route (default); "
                        "waypoints FILE (same as --waypoints FILE); trajectory FILE (same as --trajectory FILE)")
    g.add_argument("--waypoints", type=Path, default=None, help="file of 'x y' world waypoints (mobile base)")
    g.add_argument("--trajectory", type=Path, default=None,
                   help="TUM trajectory of camera poses to replay (e.g. a recording's trajectory_tum.txt)")
    p.add_argument("--steps", type=int, default=200, help="number of steps (default 200; keyboard: until x)")
    p.add_argument("--seed", type=int, default=0, help="seed of start pose, route and noise")
    p.add_argument("--dt", type=float, default=0.1, help="sim time per step, seconds")
    p.add_argument("--width", type=int, default=640, help="camera image width")
    p.add_argument("--height", type=int, default=480, help="camera image height")
    p.add_argument("--rate-hz", type=float, default=10.0, help="camera rate (Hz of sim time)")
    p.add_argument("--hfov-deg", type=float, default=None,
                   help="camera horizontal FOV (default: the capture's intrinsics rescaled)")
    p.add_argument("--tilt-deg", type=float, default=10.0, help="initial head tilt (positive looks down)")
    p.add_argument("--depth-noise", action="store_true", help="apply the seeded depth noise model")
    p.add_argument("--odom-drift", action="store_true", help="let odometry drift (seeded)")
    p.add_argument("--record", type=Path, default=None, help="record to this folder (MCAP + capture folder)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --record folder")
    p.add_argument("--viewer", nargs="?", const="native", default=None, choices=["native", "web", "rrd"],
                   help="live 3D viewer (native window, web on 127.0.0.1 while the drive runs, or rrd: file "
                        "only); with --rrd, `presim view FILE.rrd [--web]` shows it again afterwards")
    p.add_argument("--rrd", type=Path, default=None, help="also save the viewer stream to this .rrd file")
    p.add_argument("--realtime", action="store_true", help="pace steps to wall time (always on for keyboard)")
    p.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    p.set_defaults(func=run)


def _load_scene(path: Path, poses: str = "auto"):
    from presim.capture.store import is_scene_dir, load_scene

    if not path.exists():
        raise FileNotFoundError(f"{path}: scene folder not found")
    if is_scene_dir(path):
        return load_scene(path, poses=poses)
    from presim.capture.importers.registry import import_capture

    print(f"{path}: not a saved scene; importing it on the fly (save it with `presim import` to skip this)",
          file=sys.stderr)
    return import_capture(path)


def _build_robot(args, scene):
    from presim.sim.robot import DEFAULT_ROBOT_URDF, RobotConfig, free_camera_rig, load_robot

    tilt = np.radians(args.tilt_deg)
    name = args.robot
    if name is None:
        name = "default" if scene.floor is not None else "free"
    if name == "free":
        return free_camera_rig()
    urdf = DEFAULT_ROBOT_URDF if name == "default" else Path(name)
    cfg = RobotConfig(drive=args.drive)
    if args.camera_link:
        cfg = RobotConfig(drive=args.drive, camera_link=args.camera_link, camera_link_is_optical=not args.camera_link_body)
    robot = load_robot(urdf, cfg)
    if "head_tilt_joint" in robot.joint_names:
        robot = load_robot(urdf, RobotConfig(
            drive=cfg.drive, camera_link=cfg.camera_link, camera_link_is_optical=cfg.camera_link_is_optical,
            initial_joint_positions=(("head_tilt_joint", tilt),)))
    return robot


def _build_sinks(args) -> list:
    if args.record is None and args.viewer is None and args.rrd is None:
        return []
    try:
        from presim.outputs.sinks import build_sinks
    except ImportError as e:
        raise ValueError(f"--record/--viewer/--rrd need presim.outputs.sinks, which is not available ({e})") from e
    viewer = args.viewer if args.viewer is not None else ("rrd" if args.rrd is not None else None)
    params = inspect.signature(build_sinks).parameters
    if "overwrite" in params:
        return build_sinks(args.record, viewer, args.rrd, overwrite=args.overwrite)
    if args.record is not None and args.record.exists():
        if not args.overwrite:
            raise FileExistsError(f"{args.record}: already exists (pass --overwrite to replace it)")
        shutil.rmtree(args.record)
    return build_sinks(args.record, viewer, args.rrd)


def _parse_controller(args: argparse.Namespace) -> None:
    """``--controller KIND [FILE]`` -> ``args.controller`` in {None, keyboard, route} plus
    ``args.waypoints`` / ``args.trajectory``."""
    c = args.controller
    if c is None:
        return
    kind, rest = c[0], c[1:]
    if kind in ("keyboard", "route") and not rest:
        args.controller = kind
    elif kind in ("waypoints", "trajectory") and len(rest) == 1:
        setattr(args, kind, Path(rest[0]))
        args.controller = None
    else:
        raise ValueError(f"--controller {' '.join(c)}: expected 'keyboard', 'route', 'waypoints FILE' "
                         "or 'trajectory FILE'")


def run(args: argparse.Namespace) -> int:
    from presim.sensors.camera import CameraSpec
    from presim.sensors.noise import DepthNoiseConfig
    from presim.sensors.odometry import OdometryConfig
    from presim.sim.controllers import KeyboardTeleop, TrajectoryReplay, load_waypoints
    from presim.sim.routes import (KeyboardDriver, ReplayDriver, RouteDriver, WaypointDriver, free_camera_route,
                                   ground_route)
    from presim.sim.simulator import SimConfig, Simulator

    if args.steps <= 0:
        raise ValueError(f"--steps must be positive, got {args.steps}")
    _parse_controller(args)
    scene = _load_scene(args.scene, getattr(args, "scene_poses", "auto"))
    robot = _build_robot(args, scene)
    cam = CameraSpec(width=args.width, height=args.height, hfov_deg=args.hfov_deg, rate_hz=args.rate_hz,
                     noise=DepthNoiseConfig() if args.depth_noise else None)
    config = SimConfig(dt_s=args.dt, cameras=(cam,), odometry=OdometryConfig(drift=args.odom_drift))
    t_setup = time.perf_counter()
    sim = Simulator(scene, robot, config)
    if args.waypoints is not None:
        if sim.is_free:
            raise ValueError("--waypoints drive a mobile base; the free camera rig takes --trajectory")
        driver = WaypointDriver(load_waypoints(args.waypoints), robot.drive)
    elif args.trajectory is not None:
        driver = ReplayDriver(TrajectoryReplay.from_file(args.trajectory))
    elif args.controller == "keyboard":
        if not sys.stdin.isatty():
            print("keyboard: stdin is not a terminal; reading keys from it anyway", file=sys.stderr)
        driver = KeyboardDriver(KeyboardTeleop(sys.stdin))
        print(f"keyboard: {KeyboardTeleop.help}", file=sys.stderr)
    else:
        driver = None
    sinks = _build_sinks(args)
    for s in sinks:
        sim.add_sink(s)
    rng = np.random.default_rng(args.seed)
    start = driver.start_pose(sim) if driver is not None else None
    joints = driver.start_joints(sim) if driver is not None else None
    result = sim.reset(args.seed, start=start, joint_positions=joints)
    if driver is None:  # built-in route drawn from the seed
        if sim.is_free:
            driver = ReplayDriver(free_camera_route(sim, rng, args.steps))
            result = sim.reset(args.seed, start=driver.start_pose(sim))
        else:
            driver = RouteDriver(ground_route(sim, rng), sim)
    setup_s = time.perf_counter() - t_setup
    realtime = args.realtime or args.controller == "keyboard"
    steps = contacts = outside = images = 0
    dist = 0.0
    stage_ms: dict[str, float] = {}
    prev = result.T_world_base[:3, 3].copy()
    t0 = time.perf_counter()
    try:
        while steps < args.steps or args.controller == "keyboard":
            if driver.done:
                break
            result = sim.step(driver.action(sim))
            steps += 1
            contacts += result.contact
            outside += result.outside_captured_area
            images += len(result.cameras)
            p = result.T_world_base[:3, 3]
            dist += float(np.linalg.norm(p - prev))
            prev = p.copy()
            for k, v in result.timings_ms.items():
                stage_ms[k] = stage_ms.get(k, 0.0) + v
            if realtime:
                lag = t0 + steps * args.dt - time.perf_counter()
                if lag > 0:
                    time.sleep(lag)
    finally:
        driver.close()
        sim.close()
    wall = time.perf_counter() - t0
    p = result.T_world_base[:3, 3]
    print(f"drive: {sim.scene_name}  robot {robot.urdf_path.name} ({robot.drive})  seed {args.seed}")
    print(f"  steps {steps}  sim time {sim.sim_time_s:.1f} s  distance {dist:.2f} m  contacts {contacts}  "
          f"outside captured area {outside}  images {images}")
    print(f"  final base pose x {p[0]:.2f} y {p[1]:.2f} z {p[2]:.2f} yaw {np.degrees(sim.yaw):.0f} deg")
    rate = steps / wall if wall > 0 else float("inf")
    per = "  ".join(f"{k} {v / max(steps, 1):.1f}" for k, v in stage_ms.items() if k != "total")
    print(f"  {rate:.1f} steps/s ({wall:.1f} s wall, setup {setup_s:.1f} s); ms/step: {per}")
    if args.record is not None:
        print(f"  recorded to {args.record}")
    return 0
