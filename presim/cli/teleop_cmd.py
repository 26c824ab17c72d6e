"""``presim teleop``: drive a robot from a browser page served on 127.0.0.1."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

from presim.cli.sim_cmds import add_robot_arguments, robot_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "teleop",
        help="drive a robot from a web page: live colour + depth, top-down map, keyboard, recording",
        description=(
            "Start the simulator on SCENE and a web server on 127.0.0.1 serving one page: the robot camera's "
            "live colour and depth, a top-down map (click to teleport), keyboard / on-screen driving through "
            "the same controller as `presim drive`, joint sliders, reset, recording (MCAP + capture folder, "
            "as `drive --record`), snapshots, the camera pose and a camera path as a TUM file for "
            "`presim render --poses`. Open the printed URL (it carries a per-run token; requests without "
            "it, from another site's page or under another host name get 403); Ctrl-C stops. "
            "Needs the [web] group."
        ),
    )
    p.add_argument("scene", type=Path, help="saved scene folder (or a capture folder to import on the fly)")
    add_robot_arguments(p, drive_help="base motion model (holonomic: Q/E strafe; default diff)")
    p.set_defaults(drive=None)  # None = not given: the free rig warns only about an explicit --drive
    p.add_argument("--port", type=int, default=0, help="HTTP port on 127.0.0.1 (default: a free port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; anything else exposes the robot to the network)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="also accept pages of ORIGIN (http://host:port; its host is accepted as Host too); "
                        "'*' accepts any Origin and Host. Repeatable. The URL's token stays required. "
                        "Default: only the server's own page on 127.0.0.1 / localhost")
    p.add_argument("--record", type=Path, default=Path("presim_teleop"),
                   help="folder for recordings (rec_NNN/: recording.mcap + capture/) and snapshots "
                        "(default ./presim_teleop, created on first use)")
    p.add_argument("--seed", type=int, default=0, help="seed of the start pose")
    p.add_argument("--dt", type=float, default=0.1, help="sim time per step, seconds (steps run in real time)")
    p.add_argument("--width", type=int, default=640, help="camera image width")
    p.add_argument("--height", type=int, default=480, help="camera image height")
    p.add_argument("--rate-hz", type=float, default=10.0, help="camera rate (Hz of sim time)")
    p.add_argument("--hfov-deg", type=float, default=None, help="camera horizontal FOV (default: the capture's)")
    p.add_argument("--tilt-deg", type=float, default=None,
                   help="initial camera tilt, degrees, positive looks down: the head_tilt_joint of a mobile "
                        "robot (default 10), or on the free camera rig a pitch added to the captured view it "
                        "starts at (default 0); a robot without either warns that it is ignored")
    p.add_argument("--render-budget-ms", type=float, default=80.0,
                   help="stop adding capture views to a frame after this many ms (RenderConfig.time_budget_ms; "
                        "the first view is always warped and the final fill closes what is left); "
                        "0 = no budget, the full adaptive loop")
    p.add_argument("--jpeg-quality", type=int, default=80, help="JPEG quality of the images sent to the page")
    p.set_defaults(func=run)


def build_simulator(args: argparse.Namespace):
    """Scene + robot + simulator exactly as ``presim drive`` builds them (the one place teleop calls
    drive's builders)."""
    from presim.align.sfm import estimate_poses
    from presim.capture.open import open_scene
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.synthesis.renderer import RenderConfig

    scene = open_scene(args.scene, allow_capture=True, estimate_poses=estimate_poses,
                       on_import=lambda note: print(note, file=sys.stderr))
    robot = robot_from_args(_robot_args(args), scene)
    cam = CameraSpec(width=args.width, height=args.height, hfov_deg=args.hfov_deg, rate_hz=args.rate_hz)
    render = RenderConfig(time_budget_ms=args.render_budget_ms)
    return Simulator(scene, robot, SimConfig(dt_s=args.dt, cameras=(cam,), render=render))


def _robot_args(args: argparse.Namespace) -> argparse.Namespace:
    """``args`` with the defaults ``robot_from_args`` expects (--drive diff, --tilt-deg 10)."""
    return argparse.Namespace(**dict(vars(args), drive=getattr(args, "drive", None) or "diff",
                                     tilt_deg=10.0 if getattr(args, "tilt_deg", None) is None else args.tilt_deg))


def inactive_option_warnings(args: argparse.Namespace, robot) -> list[str]:
    """One line per option given on the command line that cannot act on ``robot``."""
    out = []
    name = robot.urdf_path.name
    if robot.drive == "free":
        if getattr(args, "drive", None) is not None:
            out.append(f"--drive {args.drive}: ignored by the free camera rig (it flies: R/F up/down, "
                       "I/K tilt, U/O roll)")
        if getattr(args, "camera_link", None):
            out.append(f"--camera-link {args.camera_link}: ignored by the free camera rig")
    elif getattr(args, "tilt_deg", None) is not None and "head_tilt_joint" not in robot.joint_names:
        out.append(f"--tilt-deg {args.tilt_deg:g}: robot {name} has no head_tilt_joint; ignored")
    return out


def make_recorder(record_dir: Path) -> list:
    """The sinks of ``presim drive --record DIR`` (MCAP + capture folder)."""
    from presim.outputs.sinks import build_sinks

    return build_sinks(record_dir, None, None)


def run(args: argparse.Namespace) -> int:
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as e:
        raise ImportError(f"teleop needs the [web] optional group ({e})") from e
    from presim.outputs.teleop.server import TeleopServer
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession

    if not 1 <= args.jpeg_quality <= 100:
        raise ValueError(f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in 0..65535, got {args.port}")
    for o in args.allow_origin:
        if o != "*" and not re.fullmatch(r"https?://[^/\s:]+(:\d{1,5})?/?", o):
            raise ValueError(f"--allow-origin {o!r}: expected '*' or an origin like http://host:8080")
    if args.dt <= 0:
        raise ValueError(f"--dt must be positive, got {args.dt}")
    if not args.render_budget_ms >= 0:  # also refuses NaN
        raise ValueError(f"--render-budget-ms must be >= 0, got {args.render_budget_ms}")
    sim = build_simulator(args)
    for line in inactive_option_warnings(args, sim.robot):
        print(f"presim teleop: warning: {line}", file=sys.stderr)
    pitch = float(np.radians(args.tilt_deg)) if sim.is_free and args.tilt_deg is not None else 0.0
    try:
        import mcap  # noqa: F401
        recorder = make_recorder
    except ImportError:
        recorder = None
    session = TeleopSession(sim, TeleopConfig(out_dir=args.record, seed=args.seed, jpeg_quality=args.jpeg_quality,
                                              start_pitch_rad=pitch), recorder)
    server = TeleopServer(session, args.host, args.port, allow_origins=tuple(args.allow_origin))
    print(f"presim teleop: {sim.scene_name} with {sim.robot.urdf_path.name} ({sim.robot.drive})", flush=True)
    print(f"presim teleop: open {server.url}  (Ctrl-C stops; recordings and snapshots go to {args.record})",
          flush=True)
    try:
        server.serve()
    except KeyboardInterrupt:  # Ctrl-C / SIGTERM is how a server ends: recordings were closed by serve()
        pass
    print("presim teleop: stopped", flush=True)
    if session.error is not None:
        print(f"presim teleop: error: the simulator stopped: {session.error}", file=sys.stderr)
        return 1
    return 0
