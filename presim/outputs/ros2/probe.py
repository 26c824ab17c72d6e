"""A ROS 2 client process that checks a running ``presim ros2`` node (used by the tests; handy by hand).

``python -m presim.outputs.ros2.probe e2e`` waits for the first image, then

1. listens for ``--listen-s`` seconds: image rates (color, depth) received, and what the node published
   meanwhile (its sequence numbers and source timestamps: rate, longest pause, frames lost on the way),
   sizes and encodings, camera_info, ``/clock``, ``/odom`` and the ``/tf`` + ``/tf_static`` edges seen;
2. teleports the base with ``/presim/teleport`` (``--start x y yaw``);
3. sends invalid commands (NaN, ±inf, huge twists; malformed joint commands; bad ``/initialpose``)
   and reads the dropped counters back from ``/diagnostics``, and whether the base moved;
4. drives ``/cmd_vel`` ``--speed`` m/s forward for ``--drive-s`` seconds (20 Hz) and reports the
   distance on ``/odom`` and the sim time the commands spanned (``/clock``);
5. calls ``/presim/reset`` and checks that ``/clock`` keeps increasing.

``python -m presim.outputs.ros2.probe soak --hz 1000 --seconds 10`` publishes ``/cmd_vel`` at the given
rate (a zero twist) and reports the messages sent; the color images received during the soak and what
the node published meanwhile (rate, longest pause, frames lost); and the color rate received and the
node's step rate (from ``/diagnostics``) during the soak and in the ``--before-s`` seconds before it.

Both print one JSON object on stdout. Images are taken raw (serialized) and counted; the first and
the last are deserialized to check their format. One ``SingleThreadedExecutor`` thread runs the
callbacks.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

__all__ = ["main"]

_NAN, _INF = float("nan"), float("inf")


class _Images:
    """One image topic, taken raw (serialized bytes): per message its arrival time, publication
    sequence number, source timestamp (the publisher's clock, ns), wait in the middleware before the
    callback (ms) and serialized size; the first and the last message are kept and deserialized."""

    def __init__(self):
        self.arrivals: list[tuple[float, int, int, float, int]] = []
        self.first: bytes | None = None
        self.last: bytes | None = None

    def add(self, raw: bytes, info) -> None:
        now_ns = time.time_ns()  # received_timestamp is on the system clock
        wait_ms = (now_ns - int(info.get("received_timestamp", now_ns))) * 1e-6
        self.arrivals.append((time.monotonic(), int(info.get("publication_sequence_number", 0)),
                              int(info.get("source_timestamp", 0)), wait_ms, len(raw)))
        if self.first is None:
            self.first = raw
        self.last = raw

    def times(self) -> list[float]:
        return [a[0] for a in self.arrivals]

    def report(self, name: str, t0: float, t1: float) -> dict:
        """In [t0, t1]: the rate received; what the publisher sent meanwhile (its sequence numbers over
        its source timestamps: ``published_hz``, and its longest pause between two frames received:
        ``pause_s_max``); frames lost on the way (gaps in the sequence numbers); the longest wait in
        the middleware before the callback; the distinct serialized sizes. And (width, height,
        encoding, data length) of the first and the last message received."""
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Image

        w = [a for a in self.arrivals if t0 <= a[0] <= t1]
        seq, src = [a[1] for a in w], [a[2] * 1e-9 for a in w]
        known = len(w) >= 2 and seq[0] > 0 and src[-1] > src[0] > 0
        out = {f"{name}_rate_hz": _rate([a[0] for a in w], t0, t1),
               f"{name}_published_hz": (seq[-1] - seq[0]) / (src[-1] - src[0]) if known else None,
               f"{name}_pause_s_max": max(b - a for a, b in zip(src, src[1:])) if known else None,
               f"{name}_lost": (seq[-1] - seq[0] + 1 - len(seq)) if known else None,
               f"{name}_wait_ms_max": max((a[3] for a in w), default=None),
               f"{name}_sizes": sorted({a[4] for a in w})}
        for key, raw in (("first", self.first), ("", self.last)):
            m = deserialize_message(raw, Image) if raw is not None else None
            out[f"{name}_{key}".rstrip("_")] = (m.width, m.height, m.encoding, len(m.data)) if m is not None else None
        return out


class _State:
    def __init__(self):
        self.lock = threading.Lock()
        self.images = {"color": _Images(), "depth": _Images()}
        self.info: tuple | None = None
        self.clock_s: float | None = None
        self.clock_n = 0
        self.odom: tuple[float, float] | None = None
        self.odom_n = 0
        self.tf_edges: set[tuple[str, str]] = set()
        self.static_edges: set[tuple[str, str]] = set()
        self.diag: dict[str, str] = {}
        self.diag_steps: list[tuple[float, int, int]] = []  # (receive time, the node's step count, its uptime_ms)


def _setup(node, st: _State, cam: str, reliable: bool = False):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image
    from tf2_msgs.msg import TFMessage

    def on_image(images: _Images):
        def cb(raw, info):
            with st.lock:
                images.add(raw, info)
        return cb

    def on_info(m):
        st.info = (m.width, m.height, m.distortion_model, list(m.k))

    def on_clock(m):
        with st.lock:
            st.clock_s = m.clock.sec + 1e-9 * m.clock.nanosec
            st.clock_n += 1

    def on_odom(m):
        with st.lock:
            st.odom = (m.pose.pose.position.x, m.pose.pose.position.y)
            st.odom_n += 1

    def on_tf(m, static=False):
        with st.lock:
            (st.static_edges if static else st.tf_edges).update(
                (t.header.frame_id, t.child_frame_id) for t in m.transforms)

    def on_diag(m):
        with st.lock:
            for s in m.status:
                if s.name.endswith(": commands"):
                    st.diag = {kv.key: kv.value for kv in s.values}
                    if st.diag.get("steps", "").isdigit() and st.diag.get("uptime_ms", "").isdigit():
                        st.diag_steps.append((time.monotonic(), int(st.diag["steps"]), int(st.diag["uptime_ms"])))

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    S = node.create_subscription
    ns, q = (f"/{cam}/reliable", 5) if reliable else (f"/{cam}", qos_profile_sensor_data)
    # images raw: counting a 0.9-1.2 MB message costs no deserialization in Python (_Images)
    return [S(Image, f"{ns}/color/image_raw", on_image(st.images["color"]), q, raw=True),
            S(Image, f"{ns}/depth/image_raw", on_image(st.images["depth"]), q, raw=True),
            S(CameraInfo, f"{ns}/color/camera_info", on_info, q),
            # keep last 1: the probe reads the newest /clock and /odom; with deeper queues a probe whose
            # executor falls behind works through seconds-old messages (stale positions and clocks)
            S(Clock, "/clock", on_clock, 1), S(Odometry, "/odom", on_odom, 1),
            S(TFMessage, "/tf", on_tf, 1), S(TFMessage, "/tf_static", lambda m: on_tf(m, True), latched),
            S(DiagnosticArray, "/diagnostics", on_diag, 10)]


def _rate(ts: list[float], t0: float, t1: float) -> float:
    w = [t for t in ts if t0 <= t <= t1]
    return (len(w) - 1) / (w[-1] - w[0]) if len(w) >= 2 and w[-1] > w[0] else 0.0


def _step_rate(samples: list[tuple[float, int, int]], t0: float, t1: float) -> float:
    """The node's own step (= published frame) rate from its /diagnostics reports received in [t0, t1]:
    steps over the node's own clock (``uptime_ms``), so late or bunched delivery does not change it."""
    w = [s for s in samples if t0 <= s[0] <= t1]
    return 1e3 * (w[-1][1] - w[0][1]) / (w[-1][2] - w[0][2]) if len(w) >= 2 and w[-1][2] > w[0][2] else 0.0


def _twist(vals):
    from geometry_msgs.msg import Twist

    m = Twist()
    m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z = (float(v) for v in vals)
    return m


def _joint(names, positions):
    from sensor_msgs.msg import JointState

    m = JointState()
    m.name = list(names)
    m.position = [float(p) for p in positions]
    return m


def _pose_msg(x, y, yaw, frame="map", q=None):
    from geometry_msgs.msg import PoseWithCovarianceStamped

    m = PoseWithCovarianceStamped()
    m.header.frame_id = frame
    m.pose.pose.position.x, m.pose.pose.position.y = float(x), float(y)
    qx, qy, qz, qw = q if q is not None else (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    o = m.pose.pose.orientation
    o.x, o.y, o.z, o.w = float(qx), float(qy), float(qz), float(qw)
    return m


BAD_TWISTS = [[_NAN, 0, 0, 0, 0, 0], [_INF, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, -_INF], [1e6, 0, 0, 0, 0, 0],
              [0, 1e308, 0, 0, 0, 0], [0.3, 0, 0, 0, 0, _NAN]]
BAD_JOINTS = [(["head_pan_joint"], []), (["nope"], [0.1]), (["head_pan_joint"], [_NAN]),
              (["head_pan_joint"], [1e9]), (["head_pan_joint", "head_pan_joint"], [0.1, 0.2]),
              ([f"j{i}" for i in range(2000)], [0.0] * 2000), ([], [])]


def _wait(cond, timeout_s: float, step_s: float = 0.05) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step_s)
    return cond()


def _offered_qos(node, topics: list[str]) -> dict[str, list[str]]:
    """topic -> [reliability, durability] offered by its publishers (from the ROS graph)."""
    out = {}
    for t in topics:
        infos = node.get_publishers_info_by_topic(t)
        if infos:
            q = infos[0].qos_profile
            out[t] = [q.reliability.name.lower(), q.durability.name.lower()]
    return out


def run_e2e(node, st: _State, args) -> dict:
    from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
    from nav_msgs.srv import SetMap
    from sensor_msgs.msg import JointState

    out: dict = {}
    if not _wait(lambda: st.images["color"].arrivals and st.diag_steps, args.timeout_s):
        return {"error": f"no image or /diagnostics within {args.timeout_s} s"}
    t0 = time.monotonic()
    time.sleep(args.listen_s)
    t1 = time.monotonic()
    with st.lock:
        for name, images in st.images.items():
            out.update(images.report(name, t0, t1))
        out.update(node_step_rate_hz=_step_rate(st.diag_steps, t0, t1), camera_info=st.info, clock_n=st.clock_n,
                   odom_n=st.odom_n, tf_edges=sorted(st.tf_edges), static_edges=sorted(st.static_edges))
    cmd = node.create_publisher(Twist, "/cmd_vel", 10)
    joints = node.create_publisher(JointState, "/joint_command", 10)
    initial = node.create_publisher(PoseWithCovarianceStamped, "/initialpose", 10)
    _wait(lambda: cmd.get_subscription_count() > 0 and joints.get_subscription_count() > 0
          and initial.get_subscription_count() > 0, 10.0)
    time.sleep(1.0)  # the node's side of the match can come later than ours (best effort drops until then)
    out["qos"] = _offered_qos(node, [f"/{args.camera}/color/image_raw", f"/{args.camera}/reliable/color/image_raw",
                                     "/tf", "/tf_static", "/map_cloud", "/robot_description", "/clock", "/odom"])

    # teleport to a known free pose (also checks the service)
    cli = node.create_client(SetMap, "/presim/teleport")
    out["teleport_ok"] = None
    if args.start is not None and cli.wait_for_service(timeout_sec=10.0):
        req = SetMap.Request()
        req.initial_pose = _pose_msg(*args.start)
        fut = cli.call_async(req)
        _wait(fut.done, 15.0)
        out["teleport_ok"] = bool(fut.done() and fut.result() is not None and fut.result().success)
        time.sleep(0.5)

    # invalid commands: all dropped, the node alive, the base still
    with st.lock:
        before, n_img = st.odom, len(st.images["color"].arrivals)
    for tw in BAD_TWISTS:
        cmd.publish(_twist(tw))
        time.sleep(0.03)
    for names, pos in BAD_JOINTS:
        joints.publish(_joint(names, pos))
        time.sleep(0.03)
    for m in (_pose_msg(0, 0, 0, q=(0, 0, 0, 2.0)), _pose_msg(0, 0, 0, frame="odom"), _pose_msg(_NAN, 0, 0)):
        initial.publish(m)
        time.sleep(0.03)
    time.sleep(2.5)  # two /diagnostics reports
    with st.lock:
        after = st.odom
        out.update(bad_sent={"cmd_vel": len(BAD_TWISTS), "joint_command": len(BAD_JOINTS), "initialpose": 3},
                   diagnostics=dict(st.diag), images_after_bad=len(st.images["color"].arrivals) - n_img)
    out["moved_by_bad_m"] = math.dist(before, after) if before and after else None

    # drive forward
    with st.lock:
        p0, c0 = st.odom, st.clock_s
    v = args.speed
    end = time.monotonic() + args.drive_s  # by the clock, not a count: a starved probe still drives drive_s
    while time.monotonic() < end:
        cmd.publish(_twist([v, 0, 0, 0, 0, 0]))
        time.sleep(0.05)
    with st.lock:
        c1 = st.clock_s
    time.sleep(1.5)  # the 0.5 s command timeout, then stopped
    with st.lock:
        p1 = st.odom
    out.update(drive_distance_m=math.dist(p0, p1) if p0 and p1 else None,
               drive_sim_s=(c1 - c0) if c0 is not None and c1 is not None else None, drive_speed=v)

    # /presim/reset: answered, and /clock keeps increasing across the new episode
    from std_srvs.srv import Empty

    reset = node.create_client(Empty, "/presim/reset")
    out["reset_ok"] = False
    if reset.wait_for_service(timeout_sec=10.0):
        with st.lock:
            c_before = st.clock_s
        fut = reset.call_async(Empty.Request())
        _wait(fut.done, 15.0)
        time.sleep(0.5)
        with st.lock:
            out["reset_ok"] = bool(fut.done() and fut.result() is not None)
            out["clock_after_reset_increased"] = st.clock_s is not None and c_before is not None and st.clock_s > c_before
    return out


def run_soak(node, st: _State, args) -> dict:
    from geometry_msgs.msg import Twist

    if not _wait(lambda: st.images["color"].arrivals and st.diag_steps, args.timeout_s):
        return {"error": f"no image or /diagnostics within {args.timeout_s} s"}
    cmd = node.create_publisher(Twist, "/cmd_vel", 10)
    _wait(lambda: cmd.get_subscription_count() > 0, 10.0)
    time.sleep(1.0)
    tb = time.monotonic()
    time.sleep(args.before_s)  # the rates without the flood, for comparison
    msg = _twist([0, 0, 0, 0, 0, 0])
    period = 1.0 / args.hz
    t0 = time.monotonic()
    end, sent, nxt = t0 + args.seconds, 0, t0
    while True:
        now = time.monotonic()
        if now >= end:
            break
        # a burst when behind (bounded): hold the average rate on a loaded machine
        burst = 0
        while nxt <= now and burst < 50:
            cmd.publish(msg)
            sent += 1
            nxt += period
            burst += 1
        time.sleep(max(0.0, min(nxt - time.monotonic(), 0.01)))
    t1 = time.monotonic()
    with st.lock:
        return {"sent": sent, "seconds": t1 - t0, "send_hz": sent / (t1 - t0),
                **st.images["color"].report("color", t0, t1),
                "node_step_rate_hz": _step_rate(st.diag_steps, t0, t1),
                "before_color_rate_hz": _rate(st.images["color"].times(), tb, t0),
                "before_node_step_rate_hz": _step_rate(st.diag_steps, tb, t0)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="check a running presim ros2 node")
    ap.add_argument("mode", choices=("e2e", "soak"))
    ap.add_argument("--camera", default="head_camera")
    ap.add_argument("--reliable", action="store_true",
                    help="subscribe to the reliable camera topics (/<camera>/reliable/...) instead")
    ap.add_argument("--timeout-s", type=float, default=90.0, help="wait this long for the first image")
    ap.add_argument("--listen-s", type=float, default=4.0)
    ap.add_argument("--start", type=float, nargs=3, default=None, metavar=("X", "Y", "YAW"),
                    help="teleport here before the command checks")
    ap.add_argument("--speed", type=float, default=0.3)
    ap.add_argument("--drive-s", type=float, default=2.0)
    ap.add_argument("--hz", type=float, default=1000.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--before-s", type=float, default=3.0, help="soak: measure the rates this long before the flood")
    args = ap.parse_args(argv)

    from presim.outputs.ros2.env import import_rclpy

    rclpy = import_rclpy()
    from rclpy.executors import SingleThreadedExecutor

    rclpy.init()
    node = rclpy.create_node("presim_probe")
    st = _State()
    subs = _setup(node, st, args.camera, args.reliable)  # noqa: F841 (kept alive)
    # One thread: the callbacks share the node's mutually exclusive group, so a pool adds only its
    # own overhead (a MultiThreadedExecutor took 0.11 of a core and delivered 25 ms late (median) on
    # the loaded 2 cores, this one 0.05 and 3.5 ms; docs/ros2.md, "Measured")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    try:
        out = run_e2e(node, st, args) if args.mode == "e2e" else run_soak(node, st, args)
    finally:
        # stop the executor and join its thread before destroying the node: a spin thread still in
        # rcl at interpreter exit aborts the process ("terminate called without an active exception")
        ex.shutdown(timeout_sec=10.0)
        th.join(timeout=10.0)
        node.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps(out), flush=True)
    return 0 if "error" not in out else 1


if __name__ == "__main__":
    sys.exit(main())
