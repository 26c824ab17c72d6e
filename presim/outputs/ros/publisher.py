"""The simulator sink that publishes every step on ROS 1 topics (list: docs/ros.md)."""

from __future__ import annotations

import time

import numpy as np

from presim.outputs import ros_msgs as rm
from presim.outputs.frames import BASE_FRAME, MAP_FRAME, ODOM_FRAME, build_frame_tree
from presim.outputs.mcap_recorder import camera_topics
from presim.outputs.ros.config import RosBridgeConfig
from presim.outputs.ros.env import import_rospy
from presim.outputs.ros.messages import header, pose_msg, stamp, tf_msg
from presim.sim.types import SimInfo, StepResult

__all__ = ["RosPublisherSink", "STATIC_TF_PERIOD_S"]

STATIC_TF_PERIOD_S = 1.0
"""Wall-time period at which the latched /tf_static message is re-sent."""


class RosPublisherSink:
    """Sink publishing every StepResult on ROS 1 topics. Needs an initialised rospy node.

    ``config`` is a :class:`~presim.outputs.ros.config.RosBridgeConfig` (``publisher_queue``,
    ``path_every_n_steps``); None uses its defaults."""

    def __init__(self, config=None):
        if config is None:
            config = RosBridgeConfig()
        self.config = config
        self.time_offset_s = 0.0
        self.last_stamp_s = 0.0
        self._pubs: dict = {}
        self._path_poses: list = []
        self._static_sent_wall_s: float | None = None  # time.monotonic() of the last /tf_static
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
            msg = PointCloud2(header=header(rospy, 0.0, MAP_FRAME), height=f["height"], width=f["width"],
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
        from geometry_msgs.msg import PoseStamped, PoseWithCovariance, Twist, TwistWithCovariance, Vector3
        from nav_msgs.msg import Odometry, Path
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, JointState

        off = self.time_offset_s
        t = off + float(r.sim_time_s)
        self.last_stamp_s = t
        pub = self._pubs
        pub["/clock"].publish(Clock(clock=stamp(rospy, t)))
        dynamic, static = self._tree.edges(r)
        # /tf_static is latched; it is also re-sent every STATIC_TF_PERIOD_S of wall time, because a
        # subscriber that connects while the publisher is busy can miss the latched copy (seen on a
        # loaded machine: a late listener got /tf but no static edges). tf2 accepts repeats.
        now = time.monotonic()
        if static and (self._static_sent_wall_s is None or now - self._static_sent_wall_s >= STATIC_TF_PERIOD_S):
            self._static_sent_wall_s = now
            pub["/tf_static"].publish(tf_msg(rospy, static, t))
        pub["/tf"].publish(tf_msg(rospy, dynamic, t))
        tw = np.asarray(r.odometry.twist_base, dtype=np.float64).reshape(6)
        pub["/odom"].publish(Odometry(
            header=header(rospy, t, ODOM_FRAME), child_frame_id=BASE_FRAME,
            pose=PoseWithCovariance(pose=pose_msg(r.odometry.T_odom_base), covariance=[0.0] * 36),
            twist=TwistWithCovariance(twist=Twist(Vector3(*tw[:3]), Vector3(*tw[3:])), covariance=[0.0] * 36)))
        js = r.joint_states
        pub["/joint_states"].publish(JointState(header=header(rospy, t, ""), name=list(js.names),
                                                position=[float(v) for v in js.position],
                                                velocity=[float(v) for v in js.velocity], effort=[]))
        self._path_poses.append(PoseStamped(header=header(rospy, t, MAP_FRAME), pose=pose_msg(r.T_world_base)))
        self.published_steps += 1
        if self.published_steps % self.config.path_every_n_steps == 1 or self.config.path_every_n_steps == 1:
            pub["/path"].publish(Path(header=header(rospy, t, MAP_FRAME), poses=list(self._path_poses)))
        for cam in r.cameras:
            topics = self._camera_pubs(cam.sensor_name)
            ts = off + float(cam.stamp_s)
            hdr = header(rospy, ts, cam.frame_id)
            img = rm.image_fields(cam.color)
            dep = rm.depth_fields(cam.depth_m)
            ci = rm.camera_info_fields(cam.K)
            info_msg = CameraInfo(header=hdr, height=ci["height"], width=ci["width"],
                                  distortion_model=ci["distortion_model"], D=ci["d"], K=ci["k"], R=ci["r"],
                                  P=ci["p"])
            keys = ("height", "width", "encoding", "is_bigendian", "step", "data")
            pub[topics["color"]].publish(Image(header=hdr, **{k: img[k] for k in keys}))
            pub[topics["color_info"]].publish(info_msg)
            pub[topics["depth"]].publish(Image(header=hdr, **{k: dep[k] for k in keys}))
            pub[topics["depth_info"]].publish(info_msg)

    def close(self) -> None:
        for p in self._pubs.values():
            try:
                p.unregister()
            except Exception:  # rospy may already be shut down
                pass
        self._pubs = {}
