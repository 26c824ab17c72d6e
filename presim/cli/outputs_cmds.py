"""``presim ros`` (the simulator as a ROS 1 node) and ``presim view`` (open an .rrd recording)."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
from pathlib import Path

LAUNCH_DIR = Path(__file__).resolve().parents[1] / "outputs" / "launch"


def add_node_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments every ROS node command shares (``presim ros``, ``presim ros2``)."""
    p.add_argument("scene", type=Path, help="saved scene folder")
    p.add_argument("--robot", default=None,
                   help="URDF file, 'default' (presim_bot) or 'free' (camera rig); default: by scene")
    p.add_argument("--rate-hz", type=float, default=10.0,
                   help="step and camera rate: sim dt = 1/rate, one RGB-D frame per step (default 10)")
    p.add_argument("--width", type=int, default=640, help="camera image width")
    p.add_argument("--height", type=int, default=480, help="camera image height")
    p.add_argument("--seed", type=int, default=0, help="seed of the start pose (and of /presim/reset)")
    p.add_argument("--real-time-factor", type=float, default=1.0,
                   help="sim seconds per wall second (0 = as fast as possible)")


def register(sub) -> None:
    p = sub.add_parser(
        "ros", help="run the simulator as a ROS 1 node (images, tf, odom, /clock; /cmd_vel in)",
        description="Run SCENE with a robot as a ROS 1 node: publishes color/depth/camera_info, tf, odom, "
                    "path, joint_states and /clock (sim time), latches the scene cloud on /map_cloud, "
                    "takes /cmd_vel and /joint_command, serves /presim/reset and /presim/teleport. "
                    "Starts a roscore on ROS_MASTER_URI (default http://127.0.0.1:11311) when none runs. "
                    "Topics and frames: docs/ros.md.")
    add_node_arguments(p)
    p.add_argument("--host", default="127.0.0.1", help="ROS_IP / ROS_HOSTNAME of the node (default loopback)")
    p.add_argument("--master-port", type=int, default=None,
                   help="port of the ROS master when ROS_MASTER_URI is unset (default 11311)")
    p.add_argument("--no-roscore", action="store_true", help="never start a roscore (fail if none runs)")
    p.add_argument("--max-steps", type=int, default=0, help="stop after this many steps (0 = until Ctrl-C)")
    p.add_argument("--record", type=Path, default=None, help="also record (MCAP + capture folder) here")
    p.add_argument("--rrd", type=Path, default=None, help="also save the rerun viewer stream here")
    p.add_argument("--launch", action="store_true",
                   help="run through roslaunch (presim.launch: roscore + scene + robot + controllers)")
    p.set_defaults(func=run_ros)

    v = sub.add_parser("view", help="open a recorded .rrd in the rerun viewer (native, or web on 127.0.0.1)",
                       description="Show a recording written by `presim drive --rrd` / `--viewer`: in rerun's native "
                                   "viewer, its web viewer on 127.0.0.1 (--web), or, without a display, as a still "
                                   "image of the scene, trajectory, robot and last camera images (--screenshot).")
    v.add_argument("rrd", type=Path, help=".rrd file written by --viewer / --rrd")
    v.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 instead")
    v.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                   help="write a still image of the recording to this PNG and exit (no viewer, no display needed)")
    v.add_argument("--port", type=int, default=0, help="web viewer port (0 = free port)")
    v.set_defaults(func=run_view)


def _setup_ros_env(args) -> str:
    """Loopback defaults for ROS_MASTER_URI / ROS_IP (rospy binds 127.0.0.1 when ROS_IP is loopback)."""
    port = args.master_port or 11311
    if args.master_port is not None or "ROS_MASTER_URI" not in os.environ:
        os.environ["ROS_MASTER_URI"] = f"http://{args.host}:{port}"
    os.environ.setdefault("ROS_IP", args.host)
    os.environ.setdefault("ROS_HOSTNAME", os.environ["ROS_IP"])
    return os.environ["ROS_MASTER_URI"]


def _run_launch(args) -> int:
    import shutil

    from presim.outputs.ros import master_alive, start_roscore, stop_process_group
    from presim.procs import die_with_parent

    exe = shutil.which("roslaunch")
    if exe is None:
        raise FileNotFoundError("roslaunch not found: install Debian's ros-core")
    env = dict(os.environ)
    # Our launch folder is a minimal ROS package (package.xml + presim_node) so roslaunch finds the node.
    env["ROS_PACKAGE_PATH"] = os.pathsep.join(p for p in (str(LAUNCH_DIR), env.get("ROS_PACKAGE_PATH", "")) if p)
    env["PRESIM_PYTHON"] = sys.executable
    port = env["ROS_MASTER_URI"].rsplit(":", 1)[-1].strip("/")
    cmd = [exe, "--port", port, str(LAUNCH_DIR / "presim.launch"), f"scene:={args.scene.resolve()}",
           f"robot:={args.robot or 'auto'}", f"rate_hz:={args.rate_hz}", f"width:={args.width}",
           f"height:={args.height}", f"seed:={args.seed}"]
    # Our loopback master + rosout first: roslaunch would start Debian's C++ rosout, which binds
    # 0.0.0.0 (presim/outputs/ros/master.py); with a master running it starts only the node.
    core = None
    if not master_alive(env["ROS_MASTER_URI"]):
        core = start_roscore(int(port), env)
    print("presim ros: " + " ".join(cmd), file=sys.stderr)
    # SIGINT is roslaunch's own "shut the nodes down": sent by the kernel too if presim dies
    p = subprocess.Popen(cmd, env=env, preexec_fn=die_with_parent(signal.SIGINT))
    try:
        return p.wait()
    except KeyboardInterrupt:
        p.send_signal(signal.SIGINT)
        p.wait()
        return 130
    finally:
        stop_process_group(core)


def run_ros(args: argparse.Namespace) -> int:
    from presim.limits import check_intrinsics, check_positive, check_render_memory

    check_intrinsics(args.width, args.height)
    check_positive(args.rate_hz, "--rate-hz", allow_none=False)
    check_render_memory(args.width, args.height, max_memory=args.max_memory, what="one camera frame")
    uri = _setup_ros_env(args)
    if args.launch:
        return _run_launch(args)
    from presim.outputs.ros import (RosBridge, RosBridgeConfig, import_rospy, master_alive, start_roscore,
                                    stop_process_group)
    from presim.outputs.sinks import build_sinks
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator

    import_rospy()
    from presim.capture.open import open_scene
    from presim.sim.robot import robot_for_scene

    scene = open_scene(args.scene)
    robot = robot_for_scene(None if args.robot in (None, "auto") else args.robot, scene.floor is not None)
    cam = CameraSpec(width=args.width, height=args.height, rate_hz=args.rate_hz)
    sim = Simulator(scene, robot, SimConfig(dt_s=1.0 / args.rate_hz, cameras=(cam,)))
    extra = tuple(build_sinks(args.record, None, args.rrd)) if (args.record or args.rrd) else ()
    core = None
    if not master_alive(uri):
        if args.no_roscore:
            raise ValueError(f"no ROS master at {uri} (start roscore, or drop --no-roscore)")
        port = int(uri.rsplit(":", 1)[-1].strip("/"))
        print(f"presim ros: starting roscore on {uri}", file=sys.stderr)
        core = start_roscore(port, dict(os.environ))
    # SIGTERM (rosnode kill, roslaunch shutdown) ends the loop like Ctrl-C (presim.cli.main), so
    # files are closed.
    bridge = RosBridge(sim, RosBridgeConfig(seed=args.seed, real_time_factor=args.real_time_factor,
                                            max_steps=args.max_steps), extra_sinks=extra)
    print(f"presim ros: node /presim on {uri}; scene {sim.scene_name}, robot {robot.urdf_path.name}, "
          f"{args.width}x{args.height} at {args.rate_hz:g} Hz", file=sys.stderr)
    rc = 0
    try:
        bridge.run()
    except KeyboardInterrupt:
        rc = 130  # like every long-running command (Ctrl-C, SIGTERM)
    finally:
        stop_process_group(core)
    print(f"presim ros: stopped after {bridge.steps} steps", file=sys.stderr)
    return rc


def run_view(args: argparse.Namespace) -> int:
    from presim.procs import die_with_parent, stop_group
    from presim.outputs.viewer import (ViewerError, check_rrd_file, free_port, has_display, rerun_executable,
                                       wait_for_port, web_viewer_url)

    check_rrd_file(args.rrd)
    if args.screenshot is not None:
        from presim.outputs.rrd_snapshot import write_snapshot

        rec = write_snapshot(args.rrd, args.screenshot)
        print(f"wrote {args.screenshot} ({len(rec.points_xyz)} scene points, {rec.steps} steps, "
              f"{len(rec.input_T_world_cam)} input views)")
        return 0
    if not args.web:
        if not has_display():
            raise ViewerError("no display (DISPLAY and WAYLAND_DISPLAY are unset); use --web")
        try:
            return subprocess.call(rerun_executable() + ["--bind", "127.0.0.1", str(args.rrd)])
        except KeyboardInterrupt:
            return 130
    web, grpc = args.port or free_port(), free_port()
    # Its own session: the terminal's Ctrl-C reaches presim only, which stops the viewer at once (no
    # second Ctrl-C); the kernel stops it too if presim is killed.
    p = subprocess.Popen(rerun_executable() + ["--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
                                               "--web-viewer-port", str(web), str(args.rrd)],
                         start_new_session=True, preexec_fn=die_with_parent())
    try:
        wait_for_port("127.0.0.1", web, process=p)
        print(f"presim view: {web_viewer_url('127.0.0.1', web, grpc)}  (Ctrl-C to stop)", file=sys.stderr)
        return p.wait()
    except KeyboardInterrupt:
        return 130  # like every long-running command (Ctrl-C, SIGTERM)
    finally:
        stop_group(p, signal.SIGTERM, timeout_s=2.0)
