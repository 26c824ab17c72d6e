"""ROS 1 bridge: the simulator as a ROS node (thesis §2.3, §4.3.1, §4.3.4).

rospy comes from Debian's packages (``ros-core``, ``python3-rospy``, message packages) installed in
``/usr/lib/python3/dist-packages``. The project's venv is not a ``--system-site-packages`` venv, so
:func:`import_rospy` APPENDS that folder to ``sys.path`` (at the end, so the venv's numpy, yaml etc.
win) before importing rospy. Both use Python 3.11, so the pure-Python ROS packages load as they are.

Published (stamps = sim time; ``/clock`` drives ``use_sim_time`` nodes)::

    /clock                              rosgraph_msgs/Clock
    /tf, /tf_static (latched)           tf2_msgs/TFMessage     map -> odom -> base_link -> ... -> camera_optical_frame
    /odom                               nav_msgs/Odometry      odom -> base_link
    /path                               nav_msgs/Path          ground-truth base path in map
    /joint_states                       sensor_msgs/JointState
    /map_cloud (latched)                sensor_msgs/PointCloud2 scene cloud in map
    /<camera>/color/image_raw           sensor_msgs/Image      rgb8
    /<camera>/color/camera_info         sensor_msgs/CameraInfo
    /<camera>/depth/image_raw           sensor_msgs/Image      32FC1 metres, NaN invalid (REP-118)
    /<camera>/depth/camera_info         sensor_msgs/CameraInfo

Subscribed: ``/cmd_vel`` (geometry_msgs/Twist; linear.x/.y, angular.z for a mobile base, all six for
the free rig; a command older than ``cmd_timeout_s`` wall seconds means stop) and
``/joint_command`` (sensor_msgs/JointState: ``name[]`` + ``position[]`` are joint position targets).
Services: ``/presim/reset`` (std_srvs/Empty: new episode at the seeded start pose) and
``/presim/teleport`` (nav_msgs/SetMap, the service amcl uses to set a pose: only
``initial_pose.pose.pose`` in ``map`` is used, ``map`` is ignored; it starts a new episode at that
pose, so odometry restarts there; ``success`` is false when the pose is in collision; a mobile base
keeps x, y, yaw). ``/initialpose``
(geometry_msgs/PoseWithCovarianceStamped, RViz's "2D Pose Estimate") teleports too.

Sim time keeps running forward across resets (ROS nodes drop their tf buffers when time jumps back),
so the ROS stamp is ``episode offset + sim_time_s``. Every subscriber callback only stores the latest
value under a lock (queue_size 1, rospy drops older messages), and publishers have small queues, so a
slow subscriber or a ``/cmd_vel`` flood cannot stall the loop or grow memory.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from presim.geometry import make_pose, quat_xyzw_to_R
from presim.outputs import ros_msgs as rm
from presim.outputs.frames import BASE_FRAME, MAP_FRAME, ODOM_FRAME, FrameEdge, build_frame_tree
from presim.outputs.mcap_recorder import camera_topics
from presim.sim.types import SimInfo, StepResult

__all__ = ["ROS_DIST_PACKAGES", "import_rospy", "RosBridgeConfig", "RosPublisherSink", "CommandInbox",
           "RosBridge", "ros_env", "pose_to_T", "master_alive", "start_roscore", "stop_process_group"]

ROS_DIST_PACKAGES = "/usr/lib/python3/dist-packages"


def import_rospy():
    """Import Debian's rospy from the venv (see the module docstring). Clear error when missing."""
    if ROS_DIST_PACKAGES not in sys.path and os.path.isdir(ROS_DIST_PACKAGES):
        sys.path.append(ROS_DIST_PACKAGES)  # at the END: the venv's own packages keep priority
    try:
        import rospy  # noqa: F401
    except ImportError as e:
        raise ImportError(f"rospy not found ({e}); install Debian's ROS 1 packages: "
                          "apt-get install ros-core python3-rospy ros-sensor-msgs ros-nav-msgs "
                          "ros-tf2-msgs ros-std-srvs (scripts/setup.sh --test-system)") from e
    return rospy


def ros_env(master_port: int = 11311, host: str = "127.0.0.1", base: dict | None = None) -> dict[str, str]:
    """Environment for ROS processes on ``host`` (loopback by default: rospy then binds 127.0.0.1)."""
    env = dict(os.environ if base is None else base)
    env.setdefault("ROS_MASTER_URI", f"http://{host}:{master_port}")
    env.setdefault("ROS_IP", host)
    env.setdefault("ROS_HOSTNAME", host)
    env.setdefault("ROS_HOME", os.path.join(os.path.expanduser("~"), ".ros"))
    return env


@dataclass(frozen=True)
class RosBridgeConfig:
    """ROS node settings."""

    node_name: str = "presim"
    """ROS node name."""
    cmd_timeout_s: float = 0.5
    """Wall seconds after the last /cmd_vel before the base is stopped (safety, like most drivers)."""
    real_time_factor: float = 1.0
    """Sim seconds per wall second; 0 = as fast as possible."""
    path_every_n_steps: int = 5
    """Publish /path every n steps (it grows with the drive)."""
    publisher_queue: int = 2
    """rospy publisher queue size (per subscriber; oldest dropped when a subscriber is slow)."""
    seed: int = 0
    """Seed of the start pose (and of each reset)."""
    max_steps: int = 0
    """Stop after this many steps (0 = run until Ctrl-C / rosnode kill)."""


# ---- ROS 1 message building ------------------------------------------------------------------------

def _stamp(rospy, t_s: float):
    sec, nsec = rm.split_stamp(t_s)
    return rospy.Time(sec, nsec)


def _header(rospy, t_s: float, frame_id: str):
    from std_msgs.msg import Header

    return Header(stamp=_stamp(rospy, t_s), frame_id=frame_id)


def _tf_msg(rospy, edges: list[FrameEdge], t_s: float):
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    from tf2_msgs.msg import TFMessage

    out = []
    for e in edges:
        (x, y, z), (qx, qy, qz, qw) = rm.pose_fields(e.T_parent_child)
        out.append(TransformStamped(header=_header(rospy, t_s, e.parent), child_frame_id=e.child,
                                    transform=Transform(Vector3(x, y, z), Quaternion(qx, qy, qz, qw))))
    return TFMessage(transforms=out)


def _pose_msg(T: np.ndarray):
    from geometry_msgs.msg import Point, Pose, Quaternion

    (x, y, z), (qx, qy, qz, qw) = rm.pose_fields(T)
    return Pose(Point(x, y, z), Quaternion(qx, qy, qz, qw))


def pose_to_T(pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4."""
    q = pose.orientation
    return make_pose(quat_xyzw_to_R(np.array([q.x, q.y, q.z, q.w])),
                     [pose.position.x, pose.position.y, pose.position.z])


class RosPublisherSink:
    """Sink publishing every StepResult on ROS 1 topics. Needs an initialised rospy node."""

    def __init__(self, config: RosBridgeConfig = RosBridgeConfig()):
        self.config = config
        self.time_offset_s = 0.0
        self.last_stamp_s = 0.0
        self._pubs: dict = {}
        self._path_poses: list = []
        self._static_sent = False
        self.published_steps = 0

    def open(self, info: SimInfo) -> None:
        rospy = import_rospy()
        from nav_msgs.msg import Odometry, Path
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import JointState, PointCloud2, PointField
        from tf2_msgs.msg import TFMessage

        self._rospy = rospy
        self._info = info
        self._tree = build_frame_tree(info)
        q = self.config.publisher_queue
        P = rospy.Publisher
        self._pubs = {
            "/clock": P("/clock", Clock, queue_size=10),
            "/tf": P("/tf", TFMessage, queue_size=100),
            "/tf_static": P("/tf_static", TFMessage, queue_size=10, latch=True),
            "/odom": P("/odom", Odometry, queue_size=q * 5),
            "/path": P("/path", Path, queue_size=q),
            "/joint_states": P("/joint_states", JointState, queue_size=q * 5),
            "/map_cloud": P("/map_cloud", PointCloud2, queue_size=1, latch=True),
        }
        if len(info.points_xyz):
            f = rm.cloud_fields(info.points_xyz, info.points_rgb)
            msg = PointCloud2(header=_header(rospy, 0.0, MAP_FRAME), height=f["height"], width=f["width"],
                              fields=[PointField(d["name"], d["offset"], d["datatype"], d["count"])
                                      for d in f["fields"]],
                              is_bigendian=False, point_step=f["point_step"], row_step=f["row_step"],
                              data=f["data"], is_dense=True)
            self._pubs["/map_cloud"].publish(msg)

    def _camera_pubs(self, sensor: str):
        from sensor_msgs.msg import CameraInfo, Image

        topics = camera_topics(sensor)
        if topics["color"] not in self._pubs:
            P, q = self._rospy.Publisher, self.config.publisher_queue
            self._pubs[topics["color"]] = P(topics["color"], Image, queue_size=q)
            self._pubs[topics["color_info"]] = P(topics["color_info"], CameraInfo, queue_size=q)
            self._pubs[topics["depth"]] = P(topics["depth"], Image, queue_size=q)
            self._pubs[topics["depth_info"]] = P(topics["depth_info"], CameraInfo, queue_size=q)
        return topics

    def new_episode(self) -> None:
        """Call before a reset: keeps ROS time monotonic and starts a new /path."""
        self.time_offset_s = self.last_stamp_s + (self._info.dt_s if hasattr(self, "_info") else 0.0)
        self._path_poses = []

    def on_step(self, r: StepResult) -> None:
        rospy = self._rospy
        from geometry_msgs.msg import PoseStamped, Twist, TwistWithCovariance, Vector3
        from geometry_msgs.msg import PoseWithCovariance
        from nav_msgs.msg import Odometry, Path
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, JointState

        off = self.time_offset_s
        t = off + float(r.sim_time_s)
        self.last_stamp_s = t
        pub = self._pubs
        pub["/clock"].publish(Clock(clock=_stamp(rospy, t)))
        dynamic, static = self._tree.edges(r)
        if not self._static_sent and static:
            self._static_sent = True
            pub["/tf_static"].publish(_tf_msg(rospy, static, t))
        pub["/tf"].publish(_tf_msg(rospy, dynamic, t))
        tw = np.asarray(r.odometry.twist_base, dtype=np.float64).reshape(6)
        pub["/odom"].publish(Odometry(
            header=_header(rospy, t, ODOM_FRAME), child_frame_id=BASE_FRAME,
            pose=PoseWithCovariance(pose=_pose_msg(r.odometry.T_odom_base), covariance=[0.0] * 36),
            twist=TwistWithCovariance(twist=Twist(Vector3(*tw[:3]), Vector3(*tw[3:])), covariance=[0.0] * 36)))
        js = r.joint_states
        pub["/joint_states"].publish(JointState(header=_header(rospy, t, ""), name=list(js.names),
                                                position=[float(v) for v in js.position],
                                                velocity=[float(v) for v in js.velocity], effort=[]))
        self._path_poses.append(PoseStamped(header=_header(rospy, t, MAP_FRAME), pose=_pose_msg(r.T_world_base)))
        self.published_steps += 1
        if self.published_steps % self.config.path_every_n_steps == 1 or self.config.path_every_n_steps == 1:
            pub["/path"].publish(Path(header=_header(rospy, t, MAP_FRAME), poses=list(self._path_poses)))
        for cam in r.cameras:
            topics = self._camera_pubs(cam.sensor_name)
            ts = off + float(cam.stamp_s)
            hdr = _header(rospy, ts, cam.frame_id)
            img = rm.image_fields(cam.color)
            dep = rm.depth_fields(cam.depth_m)
            ci = rm.camera_info_fields(cam.K)
            info_msg = CameraInfo(header=hdr, height=ci["height"], width=ci["width"],
                                  distortion_model=ci["distortion_model"], D=ci["d"], K=ci["k"], R=ci["r"],
                                  P=ci["p"])
            pub[topics["color"]].publish(Image(header=hdr, **{k: img[k] for k in
                                                             ("height", "width", "encoding", "is_bigendian",
                                                              "step", "data")}))
            pub[topics["color_info"]].publish(info_msg)
            pub[topics["depth"]].publish(Image(header=hdr, **{k: dep[k] for k in
                                                             ("height", "width", "encoding", "is_bigendian",
                                                              "step", "data")}))
            pub[topics["depth_info"]].publish(info_msg)

    def close(self) -> None:
        for p in self._pubs.values():
            try:
                p.unregister()
            except Exception:  # rospy may already be shut down
                pass
        self._pubs = {}


# ---- commands in -----------------------------------------------------------------------------------

class CommandInbox:
    """Latest commands from ROS callbacks (any thread), read by the step loop. Constant memory."""

    def __init__(self):
        self._lock = threading.Lock()
        self.twist = np.zeros(6)
        self.twist_wall_s = -np.inf
        self.joint_targets: dict[str, float] = {}
        self.cmd_count = 0
        self._requests: list[tuple[str, object, threading.Event, list]] = []

    def set_twist(self, twist6: np.ndarray) -> None:
        with self._lock:
            self.twist = np.asarray(twist6, dtype=np.float64).copy()
            self.twist_wall_s = time.monotonic()
            self.cmd_count += 1

    def set_joint_targets(self, targets: dict[str, float]) -> None:
        with self._lock:
            self.joint_targets.update(targets)

    def current(self, timeout_s: float) -> tuple[np.ndarray, dict[str, float]]:
        with self._lock:
            fresh = time.monotonic() - self.twist_wall_s <= timeout_s
            tw = self.twist.copy() if fresh else np.zeros(6)
            jt, self.joint_targets = self.joint_targets, {}
        return tw, jt

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


class RosBridge:
    """Runs a :class:`~presim.sim.simulator.Simulator` as a ROS node (see the module docstring)."""

    def __init__(self, sim, config: RosBridgeConfig = RosBridgeConfig(), extra_sinks: tuple = ()):
        self.sim = sim
        self.config = config
        self.inbox = CommandInbox()
        self.publisher = RosPublisherSink(config)
        self.extra_sinks = extra_sinks
        self.steps = 0
        self._stop = threading.Event()

    def stop(self) -> None:
        self._stop.set()

    def _init_node(self):
        rospy = import_rospy()
        from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
        from nav_msgs.srv import SetMap, SetMapResponse
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Empty, EmptyResponse

        rospy.set_param("/use_sim_time", True)
        # disable_signals: Ctrl-C reaches Python as KeyboardInterrupt so our finally blocks run.
        rospy.init_node(self.config.node_name, anonymous=False, disable_signals=True)
        rospy.set_param("/robot_description", self.sim.robot.urdf_xml)
        inbox = self.inbox

        def on_twist(m):
            inbox.set_twist(np.array([m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z]))

        def on_joints(m):
            if len(m.position) != len(m.name):
                rospy.logwarn("/joint_command: name[] and position[] differ in length; ignored")
                return
            inbox.set_joint_targets({n: float(p) for n, p in zip(m.name, m.position)})

        def teleport_T(pose_msg, frame_id: str):
            if frame_id not in ("", MAP_FRAME):
                raise ValueError(f"teleport pose must be in '{MAP_FRAME}', got '{frame_id}'")
            return pose_to_T(pose_msg)

        def on_reset(_req):
            inbox.request("reset", None)
            return EmptyResponse()

        def on_teleport(req):
            try:
                T = teleport_T(req.initial_pose.pose.pose, req.initial_pose.header.frame_id)
                ok = bool(inbox.request("teleport", T))
            except (ValueError, RuntimeError, TimeoutError) as e:
                rospy.logwarn(f"/presim/teleport: {e}")
                ok = False
            return SetMapResponse(success=ok)

        def on_initialpose(m):
            try:
                T = teleport_T(m.pose.pose, m.header.frame_id)
            except ValueError as e:
                rospy.logwarn(f"/initialpose: {e}")
                return
            threading.Thread(target=lambda: inbox.request("teleport", T), daemon=True).start()

        self._subs = [rospy.Subscriber("/cmd_vel", Twist, on_twist, queue_size=1),
                      rospy.Subscriber("/joint_command", JointState, on_joints, queue_size=1),
                      rospy.Subscriber("/initialpose", PoseWithCovarianceStamped, on_initialpose, queue_size=1)]
        self._srvs = [rospy.Service("/presim/reset", Empty, on_reset),
                      rospy.Service("/presim/teleport", SetMap, on_teleport)]
        return rospy

    def _handle_requests(self) -> None:
        for kind, arg, ev, box in self.inbox.take_requests():
            try:
                if kind == "reset":
                    self.publisher.new_episode()
                    self.sim.reset(self.config.seed)
                    box.append(True)
                elif kind == "teleport":
                    # A new episode starting at the pose: Action(T_world_base=...) would instead be
                    # a one-step move whose huge implied velocity the acceleration limits then carry on.
                    self.publisher.new_episode()
                    r = self.sim.reset(self.config.seed, start=arg)
                    err = np.linalg.norm(r.T_world_base[:2, 3] - np.asarray(arg)[:2, 3])
                    box.append(bool(err < 1e-3 and not r.contact))
                else:
                    box.append(ValueError(f"unknown request {kind}"))
            except Exception as e:  # answer the caller, keep the node alive
                box.append(e)
            finally:
                ev.set()

    def run(self, on_step: Callable[[StepResult], None] | None = None) -> int:
        """Spin the step loop until Ctrl-C, rospy shutdown, :meth:`stop` or ``max_steps``."""
        from presim.sim.controllers import Action

        rospy = self._init_node()
        sim, cfg = self.sim, self.config
        sim.add_sink(self.publisher)
        for s in self.extra_sinks:
            sim.add_sink(s)
        dt = sim.config.dt_s
        try:
            sim.reset(cfg.seed)
            t0 = time.monotonic()
            n_paced = 0
            while not self._stop.is_set() and not rospy.is_shutdown():
                if cfg.max_steps and self.steps >= cfg.max_steps:
                    break
                self._handle_requests()
                twist6, joints = self.inbox.current(cfg.cmd_timeout_s)
                twist = twist6 if sim.is_free else twist6[[0, 1, 5]]
                r = sim.step(Action(twist=twist, joint_targets=joints or None))
                self.steps += 1
                if on_step is not None:
                    on_step(r)
                if cfg.real_time_factor > 0:
                    n_paced += 1
                    lag = t0 + n_paced * dt / cfg.real_time_factor - time.monotonic()
                    if lag > 0:
                        self._stop.wait(lag)
                    elif lag < -1.0:  # far behind (slow render): re-anchor instead of bursting
                        t0, n_paced = time.monotonic(), 0
        finally:
            for kind, _, ev, box in self.inbox.take_requests():
                box.append(RuntimeError("node shutting down"))
                ev.set()
            sim.close()
            rospy.signal_shutdown("presim bridge stopped")
        return 0


# ---- master ----------------------------------------------------------------------------------------

def master_alive(uri: str, timeout_s: float = 1.0) -> bool:
    """True when a ROS master answers at ``uri`` (XML-RPC getPid)."""
    import socket
    import xmlrpc.client

    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout_s)
    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).getPid("/presim_check")
        return code == 1
    except (OSError, xmlrpc.client.Error):
        return False
    finally:
        socket.setdefaulttimeout(old)


def start_roscore(port: int, env: dict[str, str], timeout_s: float = 30.0, log=None):
    """Start ``roscore -p port`` in its own process group; returns the Popen once the master answers.
    Stop it with :func:`stop_process_group`."""
    import shutil
    import subprocess

    exe = shutil.which("roscore")
    if exe is None:
        raise FileNotFoundError("roscore not found: install Debian's ros-core (scripts/setup.sh --test-system)")
    p = subprocess.Popen([exe, "-p", str(port)], env=env, stdin=subprocess.DEVNULL,
                         stdout=log or subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
    uri = f"http://{env.get('ROS_IP', '127.0.0.1')}:{port}"
    deadline = time.monotonic() + timeout_s
    while not master_alive(uri):
        if p.poll() is not None or time.monotonic() > deadline:
            stop_process_group(p)
            raise RuntimeError(f"roscore on port {port} did not come up (exit code {p.returncode})")
        time.sleep(0.2)
    return p


def stop_process_group(p, timeout_s: float = 10.0) -> None:
    """SIGINT then SIGKILL the process group led by ``p`` (a process we started with start_new_session)."""
    import signal
    import subprocess

    if p is None or p.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue
