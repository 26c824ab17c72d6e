"""``presim ros2``: the simulator as a ROS 2 node (rclpy from the ``[ros2]`` group)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from presim.cli.outputs_cmds import add_node_arguments
from presim.cli.sim_cmds import REALTIME_RENDER_BUDGET_MS


def register(sub) -> None:
    p = sub.add_parser(
        "ros2", help="run the simulator as a ROS 2 node (images, tf, odom, /clock; /cmd_vel in)",
        description="Run SCENE with a robot as a ROS 2 node: publishes color/depth/camera_info (sensor-data "
                    "QoS, plus reliable copies under /<camera>/reliable/), /tf, /tf_static, /odom, /path, "
                    "/joint_states, /clock (sim time), /diagnostics, and /map_cloud and /robot_description "
                    "(transient local); takes /cmd_vel, /joint_command and /initialpose; serves /presim/reset "
                    "and /presim/teleport. Discovery stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE "
                    "is set. Topics, QoS and frames: docs/ros2.md.")
    add_node_arguments(p)
    p.add_argument("--render-budget-ms", type=float, default=REALTIME_RENDER_BUDGET_MS,
                   help="stop adding capture views to a camera frame after this many ms (0 = the full "
                        "adaptive loop)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the environment's, or 0)")
    p.add_argument("--max-steps", type=int, default=0, help="stop after this many steps (0 = until Ctrl-C)")
    p.add_argument("--record", type=Path, default=None, help="also record (rosbag2 MCAP + capture folder) here")
    p.add_argument("--rrd", type=Path, default=None, help="also save the rerun viewer stream here")
    p.set_defaults(func=run_ros2)


def run_ros2(args: argparse.Namespace) -> int:
    from presim.limits import check_intrinsics, check_positive, check_render_memory

    check_intrinsics(args.width, args.height)
    check_positive(args.rate_hz, "--rate-hz", allow_none=False)
    check_render_memory(args.width, args.height, max_memory=args.max_memory, what="one camera frame")
    if not args.render_budget_ms >= 0:  # also refuses NaN
        raise ValueError(f"--render-budget-ms must be >= 0, got {args.render_budget_ms}")
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        raise ValueError(f"--domain-id must be in 0..232, got {args.domain_id}")
    from presim.outputs.ros2 import Ros2Bridge, Ros2BridgeConfig, import_rclpy

    import_rclpy()  # a missing [ros2] group or tf2_msgs: the install line, before the scene loads
    from presim.capture.open import open_scene
    from presim.outputs.sinks import build_sinks
    from presim.sensors.camera import CameraSpec
    from presim.sim.robot import robot_for_scene
    from presim.sim.simulator import SimConfig, Simulator

    scene = open_scene(args.scene)
    robot = robot_for_scene(None if args.robot in (None, "auto") else args.robot, scene.floor is not None)
    cam = CameraSpec(width=args.width, height=args.height, rate_hz=args.rate_hz)
    cfg = SimConfig(dt_s=1.0 / args.rate_hz, cameras=(cam,))
    cfg = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, time_budget_ms=args.render_budget_ms))
    sim = Simulator(scene, robot, cfg)
    extra = tuple(build_sinks(args.record, None, args.rrd)) if (args.record or args.rrd) else ()
    bridge = Ros2Bridge(sim, Ros2BridgeConfig(seed=args.seed, real_time_factor=args.real_time_factor,
                                              max_steps=args.max_steps, domain_id=args.domain_id),
                        extra_sinks=extra)
    print(f"presim ros2: node /presim; scene {sim.scene_name}, robot {robot.urdf_path.name}, "
          f"{args.width}x{args.height} at {args.rate_hz:g} Hz", file=sys.stderr, flush=True)
    rc = 0
    try:
        bridge.run()
    except KeyboardInterrupt:
        rc = 130  # like every long-running command (Ctrl-C, SIGTERM)
    print(f"presim ros2: stopped after {bridge.steps} steps", file=sys.stderr)
    return rc
