"""``presim drive``: drive a robot through a scene and watch / record what its RGB-D camera sees."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

REALTIME_RENDER_BUDGET_MS = 80.0
"""``presim drive``'s default ``--render-budget-ms`` when steps are paced to wall time (as teleop's)."""


def add_robot_arguments(p, drive_help: str) -> None:
    """--robot, --camera-link, --camera-link-body, --drive: the robot options of `drive` and `teleop`
    (read back by :func:`robot_from_args`, with --tilt-deg)."""
    p.add_argument("--robot", default=None,
                   help="URDF file, 'default' (presim_bot) or 'free' (free-flying camera rig); "
                        "default: presim_bot, or the free rig when the scene has no floor")
    p.add_argument("--camera-link", default=None,
                   help="URDF link of the camera (OpenCV optical frame; default camera_optical_frame)")
    p.add_argument("--camera-link-body", action="store_true",
                   help="the --camera-link is a ROS body frame (x forward, z up), not an optical frame")
    p.add_argument("--drive", choices=["diff", "holonomic"], default="diff", help=drive_help)


def robot_from_args(args, scene):
    """The robot the options of :func:`add_robot_arguments` (and --tilt-deg) name, for ``scene``."""
    from presim.sim.robot import robot_for_scene

    return robot_for_scene(args.robot, scene.floor is not None, drive=args.drive, camera_link=args.camera_link,
                           camera_link_is_optical=not args.camera_link_body,
                           head_tilt_rad=float(np.radians(args.tilt_deg)))


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
    add_robot_arguments(p, drive_help="base motion model (diff: vy is clipped to 0)")
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
    p.add_argument("--keep-open", action="store_true",
                   help="with --viewer web: keep serving the web viewer after the drive ends (Ctrl-C stops it)")
    p.add_argument("--realtime", action="store_true", help="pace steps to wall time (always on for keyboard)")
    p.add_argument("--render-budget-ms", type=float, default=None,
                   help="stop adding capture views to a camera frame after this many ms "
                        "(RenderConfig.time_budget_ms; 0 = the full adaptive loop). Default: 80 when steps "
                        "are paced to wall time (--realtime, keyboard), else 0 so that a seed gives the "
                        "same images on any machine")
    p.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    p.set_defaults(func=run)


def _build_sinks(args) -> list:
    if args.record is None and args.viewer is None and args.rrd is None:
        return []
    try:
        from presim.outputs.sinks import build_sinks
    except ImportError as e:
        raise ValueError(f"--record/--viewer/--rrd need presim.outputs.sinks, which is not available ({e})") from e
    viewer = args.viewer if args.viewer is not None else ("rrd" if args.rrd is not None else None)
    if getattr(args, "keep_open", False):
        from presim.outputs.viewer import ViewerConfig

        return build_sinks(args.record, viewer, args.rrd, overwrite=args.overwrite,
                           viewer_config=ViewerConfig(keep_open=True))
    return build_sinks(args.record, viewer, args.rrd, overwrite=args.overwrite)


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


def _controller(args: argparse.Namespace):
    from presim.sim.drive import ControllerSpec

    if args.waypoints is not None:
        return ControllerSpec("waypoints", args.waypoints)
    if args.trajectory is not None:
        return ControllerSpec("trajectory", args.trajectory)
    if args.controller == "keyboard":
        return ControllerSpec("keyboard", keyboard_stream=sys.stdin)
    return ControllerSpec("route")


def run(args: argparse.Namespace) -> int:
    from presim.align.sfm import estimate_poses
    from presim.capture.open import open_scene
    from presim.limits import check_intrinsics, check_positive, check_render_memory
    from presim.sensors.camera import CameraSpec
    from presim.sensors.noise import DepthNoiseConfig
    from presim.sensors.odometry import OdometryConfig
    from presim.sim.controllers import KeyboardTeleop
    from presim.sim.drive import DriveConfig, run_drive
    from presim.sim.simulator import SimConfig

    if args.steps <= 0:
        raise ValueError(f"--steps must be positive, got {args.steps}")
    check_intrinsics(args.width, args.height)
    check_positive(args.dt, "--dt", allow_none=False)
    check_positive(args.rate_hz, "--rate-hz", allow_none=False)
    check_positive(args.hfov_deg, "--hfov-deg")
    if args.hfov_deg is not None and args.hfov_deg >= 180:
        raise ValueError(f"--hfov-deg: must be below 180, got {args.hfov_deg}")
    check_render_memory(args.width, args.height, max_memory=args.max_memory, what="one camera frame")
    if args.keep_open and args.viewer != "web":
        raise ValueError("--keep-open keeps the web viewer serving: it needs --viewer web")
    _parse_controller(args)
    scene = open_scene(args.scene, allow_capture=True, estimate_poses=estimate_poses,
                       on_import=lambda note: print(note, file=sys.stderr), poses=getattr(args, "scene_poses", "auto"))
    robot = robot_from_args(args, scene)
    cam = CameraSpec(width=args.width, height=args.height, hfov_deg=args.hfov_deg, rate_hz=args.rate_hz,
                     noise=DepthNoiseConfig() if args.depth_noise else None)
    controller = _controller(args)
    keyboard = controller.kind == "keyboard"
    budget = args.render_budget_ms
    if budget is None:
        budget = REALTIME_RENDER_BUDGET_MS if (args.realtime or keyboard) else 0.0
    if not budget >= 0:  # also refuses NaN
        raise ValueError(f"--render-budget-ms must be >= 0, got {args.render_budget_ms}")
    sim_config = SimConfig(dt_s=args.dt, cameras=(cam,), odometry=OdometryConfig(drift=args.odom_drift))
    sim_config = dataclasses.replace(sim_config, render=dataclasses.replace(sim_config.render, time_budget_ms=budget))
    if keyboard:
        if not sys.stdin.isatty():
            print("keyboard: stdin is not a terminal; reading keys from it anyway", file=sys.stderr)
        print(f"keyboard: {KeyboardTeleop.help}", file=sys.stderr)
    config = DriveConfig(steps=args.steps, seed=args.seed, realtime=args.realtime or keyboard, until_done=keyboard)
    sinks: list = []

    def make_sinks() -> list:
        sinks.extend(_build_sinks(args))
        return sinks

    st = run_drive(scene, robot, sim_config, controller, config, make_sinks=make_sinks)
    p = st.T_world_base[:3, 3]
    print(f"drive: {st.scene_name}  robot {robot.urdf_path.name} ({robot.drive})  seed {args.seed}")
    print(f"  steps {st.steps}  sim time {st.sim_time_s:.1f} s  distance {st.distance_m:.2f} m  contacts {st.contacts}  "
          f"outside captured area {st.outside_captured_area}  images {st.images}")
    print(f"  final base pose x {p[0]:.2f} y {p[1]:.2f} z {p[2]:.2f} yaw {np.degrees(st.yaw_rad):.0f} deg")
    per = "  ".join(f"{k} {v:.1f}" for k, v in st.stage_ms_per_step.items() if k != "total")
    print(f"  {st.steps_per_s:.1f} steps/s ({st.wall_s:.1f} s wall, setup {st.setup_s:.1f} s); ms/step: {per}")
    for path in _written_paths(args):
        print(f"wrote {path}")
    if st.ended_early:
        print(f"note: {st.ended_early} (--steps {args.steps} not reached)", file=sys.stderr)
    _wait_for_kept_viewers(sinks)
    return 0


def _written_paths(args: argparse.Namespace) -> list[Path]:
    """The files and folders the sinks of ``args`` wrote (those that exist after the drive)."""
    from presim.outputs.sinks import CAPTURE_DIR, RECORDING_NAME

    paths = []
    if args.record is not None:
        paths += [args.record / RECORDING_NAME, args.record / CAPTURE_DIR]
    if args.rrd is not None:
        paths.append(args.rrd)
    elif args.viewer == "rrd" and args.record is not None:
        paths.append(args.record / "recording.rrd")
    return [p for p in paths if p.exists()]


def _wait_for_kept_viewers(sinks: list) -> None:
    """``--keep-open``: the web viewer keeps serving after the drive until Ctrl-C / SIGTERM."""
    for s in sinks:
        viewer = getattr(s, "inner", s)
        if getattr(viewer, "kept_open", False):
            print(f"  web viewer still serving at {viewer.url} (Ctrl-C stops it)", flush=True)
            viewer.wait_closed()
