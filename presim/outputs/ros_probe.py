"""A small ROS 1 client for checking a running ``presim ros`` node from a separate process.

    python -m presim.outputs.ros_probe listen --seconds 4          # image rate, tf tree, clock
    python -m presim.outputs.ros_probe teleport 2.5 2.0 3.1416     # /presim/teleport (nav_msgs/SetMap)
    python -m presim.outputs.ros_probe reset                       # /presim/reset (std_srvs/Empty)
    python -m presim.outputs.ros_probe drive --vx 0.3 --seconds 2  # /cmd_vel, odometry before/after
    python -m presim.outputs.ros_probe flood --count 2000 --seconds 5
    python -m presim.outputs.ros_probe joints head_pan_joint 0.5   # /joint_command, then /joint_states

Each prints one JSON object on stdout. ROS_MASTER_URI / ROS_IP come from the environment.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

import numpy as np

from presim.geometry import make_pose, quat_xyzw_to_R
from presim.outputs.ros import import_rospy, pose_to_T

__all__ = ["main"]


def _yaw(T: np.ndarray) -> float:
    return math.atan2(T[1, 0], T[0, 0])


class _Watch:
    """Collects what a ROS client sees (callbacks run in rospy threads)."""

    def __init__(self, rospy, camera: str):
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Image
        from tf2_msgs.msg import TFMessage

        self.lock = threading.Lock()
        self.image_wall_s: list[float] = []
        self.image_sizes: set[tuple[int, int, str]] = set()
        self.depth_count = 0
        self.edges: dict[str, str] = {}
        self.clock_s = None
        self.odom = None  # (T_odom_base, twist x, stamp)
        self.map_base = None
        subs = [
            rospy.Subscriber(f"/{camera}/color/image_raw", Image, self._img, queue_size=5),
            rospy.Subscriber(f"/{camera}/depth/image_raw", Image, self._depth, queue_size=5),
            rospy.Subscriber("/tf", TFMessage, self._tf, queue_size=50),
            rospy.Subscriber("/tf_static", TFMessage, self._tf, queue_size=5),
            rospy.Subscriber("/clock", Clock, self._clock, queue_size=5),
            rospy.Subscriber("/odom", Odometry, self._odom, queue_size=5),
        ]
        self.subs = subs
        self._tf_T: dict[str, np.ndarray] = {}

    def _img(self, m):
        with self.lock:
            self.image_wall_s.append(time.monotonic())
            self.image_sizes.add((m.width, m.height, m.encoding))

    def _depth(self, m):
        with self.lock:
            self.depth_count += 1

    def _tf(self, m):
        with self.lock:
            for t in m.transforms:
                self.edges[t.child_frame_id] = t.header.frame_id
                tr, q = t.transform.translation, t.transform.rotation
                self._tf_T[t.child_frame_id] = make_pose(quat_xyzw_to_R(np.array([q.x, q.y, q.z, q.w])),
                                                         [tr.x, tr.y, tr.z])
            if "odom" in self._tf_T and "base_link" in self._tf_T:
                self.map_base = self._tf_T["odom"] @ self._tf_T["base_link"]

    def _clock(self, m):
        with self.lock:
            self.clock_s = m.clock.to_sec()

    def _odom(self, m):
        with self.lock:
            self.odom = (pose_to_T(m.pose.pose), m.twist.twist.linear.x, m.header.stamp.to_sec())

    def chain(self, frame: str) -> list[str]:
        out = [frame]
        while out[-1] in self.edges and len(out) < 32:
            out.append(self.edges[out[-1]])
        return out


def _wait(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return False


_BAD_FLOATS = (float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1e6, 5e-324)


def _fuzz(rospy, hz: float, seconds: float, seed: int) -> dict:
    """Publish random and adversarial commands at ``hz`` for ``seconds`` (round-robin over the
    three command topics); returns counts per kind."""
    import random

    from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
    from sensor_msgs.msg import JointState

    rng = random.Random(seed)
    pubs = {"cmd_vel": rospy.Publisher("/cmd_vel", Twist, queue_size=1000),
            "joint_command": rospy.Publisher("/joint_command", JointState, queue_size=1000),
            "initialpose": rospy.Publisher("/initialpose", PoseWithCovarianceStamped, queue_size=1000)}
    _wait(lambda: all(p.get_num_connections() > 0 for p in pubs.values()), 20.0)

    def num():
        r = rng.random()
        return rng.choice(_BAD_FLOATS) if r < 0.4 else rng.uniform(-2.0, 2.0) if r < 0.9 else rng.uniform(-1e9, 1e9)

    def name():
        r = rng.random()
        if r < 0.4:
            return rng.choice(["head_pan_joint", "head_tilt_joint"])
        if r < 0.7:
            return rng.choice(["nope", "", " ", "base_link", "head_pan_joint\x00", "ü" * 50, "/joint"])
        return "".join(chr(rng.randrange(32, 0x3000)) for _ in range(rng.randrange(0, 300)))

    def make(kind: str):
        if kind == "cmd_vel":
            m = Twist()
            m.linear.x, m.linear.y, m.linear.z = num(), num(), num()
            m.angular.x, m.angular.y, m.angular.z = num(), num(), num()
        elif kind == "joint_command":
            k = rng.choice([0, 1, 2, 3, 2000])
            names = [name()] * k if k > 3 else [name() for _ in range(k)]
            pos = [num() for _ in range(k + rng.choice([0, 0, 0, -1, 1]) if k else rng.choice([0, 1]))]
            m = JointState(name=names, position=pos)
        else:
            m = PoseWithCovarianceStamped()
            m.header.frame_id = rng.choice(["map", "", "odom", "ü" * 10])
            pp = m.pose.pose
            pp.position.x, pp.position.y, pp.position.z = num(), num(), num()
            o = pp.orientation
            o.x, o.y, o.z, o.w = num(), num(), num(), num()
        return m

    # Messages are made before the timed loop (a pool per topic, cycled), so the send rate is the
    # transport's, not the random generator's.
    kinds = ("cmd_vel", "joint_command", "initialpose")
    pool = {k: [make(k) for _ in range(400)] for k in kinds}
    sent = {k: 0 for k in pubs}
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < seconds:
        kind = kinds[n % 3]
        pubs[kind].publish(pool[kind][(n // 3) % 400])
        sent[kind] += 1
        n += 1
        lag = t0 + n / hz - time.monotonic()
        if lag > 0:
            time.sleep(lag)
    wall = time.monotonic() - t0
    return {"sent": n, "sent_per_topic": sent, "wall_s": wall, "rate_hz": n / wall}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="ros_probe", description=__doc__.split("\n")[0])
    ap.add_argument("--camera", default="head_camera")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("listen")
    p.add_argument("--seconds", type=float, default=4.0)
    p = sub.add_parser("teleport")
    p.add_argument("x", type=float)
    p.add_argument("y", type=float)
    p.add_argument("yaw", type=float)
    sub.add_parser("reset")
    p = sub.add_parser("drive")
    p.add_argument("--vx", type=float, default=0.3)
    p.add_argument("--wz", type=float, default=0.0)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--hz", type=float, default=20.0)
    p.add_argument("--settle", type=float, default=2.0, help="wait after the last command, seconds")
    p = sub.add_parser("joints")
    p.add_argument("name")
    p.add_argument("position", type=float)
    p.add_argument("--seconds", type=float, default=3.0)
    p = sub.add_parser("flood")
    p.add_argument("--count", type=int, default=2000)
    p.add_argument("--seconds", type=float, default=5.0)
    p = sub.add_parser("fuzz", help="random and adversarial /cmd_vel, /joint_command, /initialpose")
    p.add_argument("--hz", type=float, default=1000.0)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("diagnostics", help="print the next /diagnostics counters")
    p.add_argument("--timeout", type=float, default=10.0)
    args = ap.parse_args(argv)

    rospy = import_rospy()
    rospy.init_node("presim_probe", anonymous=True, disable_signals=True)
    out: dict = {}
    try:
        if args.cmd == "listen":
            w = _Watch(rospy, args.camera)
            _wait(lambda: w.image_wall_s, 30.0)
            with w.lock:
                n0 = len(w.image_wall_s)
            t0 = time.monotonic()
            time.sleep(args.seconds)
            with w.lock:
                n1 = len(w.image_wall_s)
                out = {"images": n1, "image_rate_hz": (n1 - n0) / (time.monotonic() - t0),
                       "image_sizes": sorted(w.image_sizes), "depth_images": w.depth_count,
                       "tf_edges": sorted(w.edges.items()), "camera_chain": w.chain("camera_optical_frame"),
                       "clock_s": w.clock_s}
        elif args.cmd in ("teleport", "reset"):
            w = _Watch(rospy, args.camera)
            if args.cmd == "reset":
                from std_srvs.srv import Empty

                rospy.wait_for_service("/presim/reset", 20)
                rospy.ServiceProxy("/presim/reset", Empty)()
                out = {"ok": True}
            else:
                from geometry_msgs.msg import PoseWithCovarianceStamped
                from nav_msgs.msg import OccupancyGrid
                from nav_msgs.srv import SetMap

                rospy.wait_for_service("/presim/teleport", 20)
                req_pose = PoseWithCovarianceStamped()
                req_pose.header.frame_id = "map"
                req_pose.pose.pose.position.x, req_pose.pose.pose.position.y = args.x, args.y
                req_pose.pose.pose.orientation.z = math.sin(args.yaw / 2)
                req_pose.pose.pose.orientation.w = math.cos(args.yaw / 2)
                resp = rospy.ServiceProxy("/presim/teleport", SetMap)(OccupancyGrid(), req_pose)
                out = {"ok": bool(resp.success)}
            time.sleep(0.5)
            _wait(lambda: w.map_base is not None, 10.0)
            with w.lock:
                if w.map_base is not None:
                    out["map_base_xy_yaw"] = [w.map_base[0, 3], w.map_base[1, 3], _yaw(w.map_base)]
        elif args.cmd == "drive":
            from geometry_msgs.msg import Twist

            w = _Watch(rospy, args.camera)
            pub = rospy.Publisher("/cmd_vel", Twist, queue_size=10)
            _wait(lambda: w.odom is not None and w.map_base is not None and pub.get_num_connections() > 0, 20.0)
            time.sleep(0.3)
            with w.lock:
                T0, _, s0 = w.odom
                M0 = w.map_base.copy()
            cmd = Twist()
            cmd.linear.x, cmd.angular.z = args.vx, args.wz
            t_end = time.monotonic() + args.seconds
            moving_stamps = []
            while time.monotonic() < t_end:
                pub.publish(cmd)
                time.sleep(1.0 / args.hz)
                with w.lock:
                    if w.odom is not None:
                        moving_stamps.append(w.odom[2])
            time.sleep(args.settle)
            with w.lock:
                T1, v1, s1 = w.odom
                M1 = w.map_base.copy()
            d = T1[:3, 3] - T0[:3, 3]
            out = {"odom_start": [T0[0, 3], T0[1, 3], _yaw(T0)], "odom_end": [T1[0, 3], T1[1, 3], _yaw(T1)],
                   "distance_m": float(np.linalg.norm(d[:2])),
                   "forward_m": float(d[:2] @ T0[:2, 0]),
                   "map_distance_m": float(np.linalg.norm(M1[:2, 3] - M0[:2, 3])),
                   "sim_s_during_commands": (moving_stamps[-1] - moving_stamps[0]) if moving_stamps else 0.0,
                   "sim_s_total": s1 - s0, "final_vx": v1}
        elif args.cmd == "joints":
            from sensor_msgs.msg import JointState

            last = {}
            rospy.Subscriber("/joint_states", JointState,
                             lambda m: last.update(dict(zip(m.name, m.position))), queue_size=5)
            pub = rospy.Publisher("/joint_command", JointState, queue_size=1, latch=True)
            _wait(lambda: pub.get_num_connections() > 0 and last, 20.0)
            start = dict(last)
            pub.publish(JointState(name=[args.name], position=[args.position]))
            time.sleep(args.seconds)
            out = {"start": start, "end": dict(last)}
        elif args.cmd == "flood":
            from geometry_msgs.msg import Twist

            pub = rospy.Publisher("/cmd_vel", Twist, queue_size=100)
            _wait(lambda: pub.get_num_connections() > 0, 20.0)
            cmd = Twist()
            cmd.angular.z = 0.1
            t0 = time.monotonic()
            for i in range(args.count):
                pub.publish(cmd)
                lag = t0 + (i + 1) * args.seconds / args.count - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
            out = {"sent": args.count, "wall_s": time.monotonic() - t0}
        elif args.cmd == "fuzz":
            out = _fuzz(rospy, args.hz, args.seconds, args.seed)
        elif args.cmd == "diagnostics":
            from diagnostic_msgs.msg import DiagnosticArray

            got = []
            rospy.Subscriber("/diagnostics", DiagnosticArray, lambda m: got.append(m), queue_size=5)
            _wait(lambda: got, args.timeout)
            st = got[-1].status[0] if got else None
            out = {} if st is None else {"level": int.from_bytes(st.level, "little") if isinstance(st.level, bytes)
                                         else int(st.level), "name": st.name, "message": st.message,
                                         "values": {kv.key: kv.value for kv in st.values}}
    finally:
        rospy.signal_shutdown("probe done")
    print(json.dumps(out, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
