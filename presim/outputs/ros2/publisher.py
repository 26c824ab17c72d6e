"""The simulator sink that publishes every step on ROS 2 topics (list and QoS: docs/ros2.md)."""

from __future__ import annotations

import numpy as np

from presim.outputs import ros_msgs as rm
from presim.outputs.frames import BASE_FRAME, MAP_FRAME, ODOM_FRAME, build_frame_tree
from presim.outputs.mcap_recorder import camera_topics
from presim.outputs.ros2.messages import make, qos_profiles
from presim.sim.types import SimInfo, StepResult

__all__ = ["Ros2PublisherSink", "RELIABLE_NS"]

RELIABLE_NS = "reliable"
"""Camera topics are also offered reliably under ``/<camera>/reliable/...``."""


class Ros2PublisherSink:
    """Sink publishing every StepResult on ROS 2 topics from an rclpy ``node``.

    ``config`` is a :class:`~presim.outputs.ros2.node.Ros2BridgeConfig` (``path_every_n_steps``,
    ``reliable_camera_topics``). Camera messages are only built for publishers that have a
    subscriber (a 640x480 RGB-D frame is 2.1 MB to copy)."""

    def __init__(self, config, node=None):
        self.config = config
        self.node = node
        self.time_offset_s = 0.0
        self.last_stamp_s = 0.0
        self._pubs: dict = {}
        self._path_stamps: list[float] = []
        self._path_poses: list[np.ndarray] = []
        self._static_sent = False
        self._info: SimInfo | None = None
        self.published_steps = 0

    def open(self, info: SimInfo) -> None:
        if self.node is None:
            raise RuntimeError("Ros2PublisherSink needs an rclpy node (Ros2Bridge sets it)")
        from nav_msgs.msg import Odometry, Path
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import JointState, PointCloud2
        from std_msgs.msg import String
        from tf2_msgs.msg import TFMessage

        self._info = info
        self._tree = build_frame_tree(info)
        q = self._qos = qos_profiles()
        P = self.node.create_publisher
        self._pubs = {
            "/clock": P(Clock, "/clock", q["default"]),
            "/tf": P(TFMessage, "/tf", q["tf"]),
            "/tf_static": P(TFMessage, "/tf_static", q["latched"]),
            "/odom": P(Odometry, "/odom", q["default"]),
            "/path": P(Path, "/path", q["default"]),
            "/joint_states": P(JointState, "/joint_states", q["default"]),
            "/map_cloud": P(PointCloud2, "/map_cloud", q["latched"]),
            "/robot_description": P(String, "/robot_description", q["latched"]),
        }
        if info.urdf_xml:
            self._pubs["/robot_description"].publish(String(data=info.urdf_xml))
        if len(info.points_xyz):
            self._pubs["/map_cloud"].publish(make(PointCloud2, rm.ros2_point_cloud(
                info.points_xyz, info.points_rgb, 0.0, MAP_FRAME)))

    def _camera_pubs(self, sensor: str) -> list[tuple[dict[str, str], dict]]:
        """``[(topic names, publishers)]``: the sensor-data topics, then the reliable variant."""
        from sensor_msgs.msg import CameraInfo, Image

        out = []
        variants = [(sensor, "sensor")]
        if self.config.reliable_camera_topics:
            variants.append((f"{sensor.strip('/')}/{RELIABLE_NS}", "reliable_sensor"))
        for name, qos in variants:
            topics = camera_topics(name)
            if topics["color"] not in self._pubs:
                P, q = self.node.create_publisher, self._qos[qos]
                for key, cls in (("color", Image), ("color_info", CameraInfo), ("depth", Image),
                                 ("depth_info", CameraInfo)):
                    self._pubs[topics[key]] = P(cls, topics[key], q)
            out.append((topics, {k: self._pubs[t] for k, t in topics.items()}))
        return out

    def new_episode(self) -> None:
        """Call before a reset: keeps ROS time monotonic and starts a new /path."""
        self.time_offset_s = self.last_stamp_s + (self._info.dt_s if self._info is not None else 0.0)
        self._path_stamps, self._path_poses = [], []

    def on_step(self, r: StepResult) -> None:
        from nav_msgs.msg import Odometry, Path
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, JointState
        from tf2_msgs.msg import TFMessage

        off = self.time_offset_s
        t = off + float(r.sim_time_s)
        self.last_stamp_s = t
        pub = self._pubs
        pub["/clock"].publish(make(Clock, rm.ros2_clock(t)))
        dynamic, static = self._tree.edges(r)
        if static and not self._static_sent:  # transient local: late subscribers get this one
            self._static_sent = True
            pub["/tf_static"].publish(make(TFMessage, rm.ros2_tf(static, t)))
        pub["/tf"].publish(make(TFMessage, rm.ros2_tf(dynamic, t)))
        pub["/odom"].publish(make(Odometry, rm.ros2_odometry(r.odometry.T_odom_base, r.odometry.twist_base, t,
                                                             ODOM_FRAME, BASE_FRAME)))
        js = r.joint_states
        pub["/joint_states"].publish(make(JointState, rm.ros2_joint_state(js.names, js.position, js.velocity, t)))
        self._path_stamps.append(t)
        self._path_poses.append(np.asarray(r.T_world_base, dtype=np.float64).copy())
        self.published_steps += 1
        n = self.config.path_every_n_steps
        if n == 1 or self.published_steps % n == 1:
            pub["/path"].publish(make(Path, rm.ros2_path(self._path_stamps, self._path_poses, MAP_FRAME)))
        for cam in r.cameras:
            ts = off + float(cam.stamp_s)
            color = depth = info = None
            for _topics, pubs in self._camera_pubs(cam.sensor_name):
                if pubs["color"].get_subscription_count():
                    color = color if color is not None else make(Image, rm.ros2_image(cam.color, ts, cam.frame_id))
                    pubs["color"].publish(color)
                if pubs["depth"].get_subscription_count():
                    depth = depth if depth is not None else make(Image, rm.ros2_depth(cam.depth_m, ts, cam.frame_id))
                    pubs["depth"].publish(depth)
                if pubs["color_info"].get_subscription_count() or pubs["depth_info"].get_subscription_count():
                    info = info if info is not None else make(CameraInfo, rm.ros2_camera_info(cam.K, ts, cam.frame_id))
                    pubs["color_info"].publish(info)
                    pubs["depth_info"].publish(info)

    def close(self) -> None:
        # The publishers go with the node (Ros2Bridge destroys it after stopping its executor):
        # destroying them here, while the executor may still run, races with it.
        self._pubs = {}
