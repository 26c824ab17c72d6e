"""Record a drive as a ROS 2 bag in one MCAP file (``ros2 bag``, Foxglove and rosbags read it).

Written with ``mcap`` (container) + ``mcap_ros2`` (CDR encoding). Topics (frames in docs/ros.md)::

    /clock                            rosgraph_msgs/msg/Clock    sim time, one per step (as the ROS 1 bridge)
    /tf                               tf2_msgs/msg/TFMessage     map->odom, odom->base_link, moving joints
    /tf_static                        tf2_msgs/msg/TFMessage     fixed joints, once (transient_local)
    /map_cloud                        sensor_msgs/msg/PointCloud2 scene cloud in map, once (transient_local)
    /robot_description                std_msgs/msg/String        the URDF, once (transient_local; Foxglove draws it)
    /odom                             nav_msgs/msg/Odometry      odom -> base_link (may drift)
    /path                             nav_msgs/msg/Path          ground-truth base path in map
    /joint_states                     sensor_msgs/msg/JointState
    /<sensor>/color/image_raw         sensor_msgs/msg/Image      rgb8
    /<sensor>/color/camera_info       sensor_msgs/msg/CameraInfo
    /<sensor>/depth/image_raw         sensor_msgs/msg/Image      32FC1 metres, NaN invalid (REP-118)
    /<sensor>/depth/camera_info       sensor_msgs/msg/CameraInfo

Every stamp (header and MCAP log time) is sim time. At close, ``metadata.yaml`` is written beside
the file (:mod:`presim.outputs.rosbag2`), so the folder is a rosbag2 bag. The file is written to ``<path>.partial`` and
renamed to ``<path>`` when closed, so a complete-looking file is always a finished one; ``close`` is
also registered with ``atexit`` so an interpreter exit after Ctrl-C still finishes the file. Every
``flush_every_n_steps`` steps the chunk in progress is written out, so a killed process leaves a
``.partial`` of complete chunks that ``presim recover`` turns into an indexed file.
"""

from __future__ import annotations

import atexit
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.outputs import ros_msgs as rm
from presim.outputs.frames import BASE_FRAME, MAP_FRAME, ODOM_FRAME, build_frame_tree, stamp_ns
from presim.outputs.rosbag2 import write_rosbag2_metadata
from presim.sim.types import SimInfo, StepResult

__all__ = ["McapConfig", "McapRecorder", "camera_topics", "LATCHED_QOS"]

# ROS 2 Humble ``offered_qos_profiles`` of a latched publisher (reliable, transient_local, keep last 1),
# so ``ros2 bag play`` re-publishes /tf_static and /map_cloud to late subscribers.
LATCHED_QOS = (
    "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
    "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
    "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  avoid_ros_namespace_conventions: false\n"
)
_LATCHED = {"/tf_static", "/map_cloud", "/robot_description"}


def camera_topics(sensor_name: str) -> dict[str, str]:
    """Topic names of one camera (same names in MCAP and on the live ROS bridge)."""
    ns = "/" + sensor_name.strip("/")
    return {"color": f"{ns}/color/image_raw", "color_info": f"{ns}/color/camera_info",
            "depth": f"{ns}/depth/image_raw", "depth_info": f"{ns}/depth/camera_info"}


@dataclass(frozen=True)
class McapConfig:
    """MCAP recorder settings."""

    compression: str = "zstd"
    """Chunk compression: ``zstd`` (smaller), ``lz4`` (faster) or ``none``."""
    chunk_size_bytes: int = 4 * 1024 * 1024
    """Uncompressed chunk size before a chunk is compressed and written."""
    path_every_n_steps: int = 10
    """Publish /path every n steps (it grows with the drive) and always at close."""
    write_cloud: bool = True
    """Write the scene point cloud once on /map_cloud."""
    flush_every_n_steps: int = 10
    """Finish the chunk in progress and flush the file every n steps: a recording killed with
    SIGKILL keeps every step but the last < n (``presim recover`` indexes it). Smaller chunks compress
less: 10 made 100 toy-room steps 4.4 % larger at 64x48 and 2.1 % at 320x240 than one chunk per 4 MB."""


class McapRecorder:
    """A :class:`~presim.sim.types.Sink` writing one ROS 2 MCAP file. Synchronous: wrap it in
    :class:`~presim.outputs.queue.QueuedSink` to keep it off the step loop."""

    def __init__(self, path: str | os.PathLike, config: McapConfig = McapConfig()):
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise ValueError(f"{self.path}: an MCAP recording must end in .mcap")
        if config.compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"unknown MCAP compression {config.compression!r} (zstd, lz4, none)")
        self.config = config
        self.partial_path = self.path.with_name(self.path.name + ".partial")
        self._writer = None
        self._file = None
        self._lock = threading.Lock()
        self._path_stamps: list[float] = []
        self._path_poses: list[np.ndarray] = []
        self._last_stamp_s = 0.0
        self._steps = 0
        self._static_done = False
        self.message_counts: dict[str, int] = {}

    # -- Sink -----------------------------------------------------------------------------------
    def open(self, info: SimInfo) -> None:
        from mcap.writer import CompressionType, Writer
        from mcap_ros2 import __version__ as mcap_ros2_version
        from mcap_ros2._dynamic import serialize_dynamic

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tree = build_frame_tree(info)
        self._info = info
        self._file = open(self.partial_path, "wb")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}[self.config.compression]
        self._writer = Writer(self._file, chunk_size=self.config.chunk_size_bytes, compression=comp)
        self._writer.start(profile="ros2", library=f"presim mcap-ros2-support/{mcap_ros2_version}")
        self._schemas: dict[str, int] = {}
        self._encoders = {}
        for t, text in rm.MSGDEFS.items():
            self._schemas[t] = self._writer.register_schema(t, "ros2msg", text.encode())
            self._encoders[t] = serialize_dynamic(t, text)[t]
        self._channels: dict[str, int] = {}
        self._writer.add_metadata("presim", {"scene": info.scene_name, "dt_s": repr(info.dt_s),
                                             "depth_encoding": "32FC1 metres, NaN = invalid"})
        atexit.register(self.close)
        if info.urdf_xml:
            self._write("/robot_description", "std_msgs/msg/String", {"data": info.urdf_xml}, 0.0)
        if self.config.write_cloud and len(info.points_xyz):
            self._write("/map_cloud", "sensor_msgs/msg/PointCloud2",
                        rm.ros2_point_cloud(info.points_xyz, info.points_rgb, 0.0, MAP_FRAME), 0.0)

    def on_step(self, result: StepResult) -> None:
        with self._lock:
            if self._writer is None:
                raise RuntimeError(f"{self.path}: recorder is closed")
            self._record(result)
            if self._steps % max(1, self.config.flush_every_n_steps) == 0:
                self._writer.flush()  # complete chunks on disk: what recovery keeps

    def close(self) -> None:
        with self._lock:
            if self._writer is None:
                return
            try:
                if self._path_stamps and self._steps % self.config.path_every_n_steps != 0:
                    self._write_path()
                self._writer.finish()
            finally:
                self._file.close()
                self._writer = None
                atexit.unregister(self.close)
            os.replace(self.partial_path, self.path)
            write_rosbag2_metadata(self.path)  # the folder becomes a rosbag2 bag (ros2 bag info/play)

    # -- internals ------------------------------------------------------------------------------
    def _write(self, topic: str, msgtype: str, msg: dict, stamp_s: float) -> None:
        cid = self._channels.get(topic)
        if cid is None:
            meta = {"offered_qos_profiles": LATCHED_QOS} if topic in _LATCHED else {}
            cid = self._writer.register_channel(topic, "cdr", self._schemas[msgtype], meta)
            self._channels[topic] = cid
        t = stamp_ns(stamp_s)
        seq = self.message_counts.get(topic, 0)
        self._writer.add_message(cid, log_time=t, data=self._encoders[msgtype](msg), publish_time=t,
                                 sequence=seq)
        self.message_counts[topic] = seq + 1

    def _write_path(self) -> None:
        self._write("/path", "nav_msgs/msg/Path",
                    rm.ros2_path(self._path_stamps, self._path_poses, MAP_FRAME), self._last_stamp_s)

    def _record(self, r: StepResult) -> None:
        t = float(r.sim_time_s)
        self._write("/clock", "rosgraph_msgs/msg/Clock", rm.ros2_clock(t), t)
        dynamic, static = self._tree.edges(r)
        if not self._static_done:
            self._static_done = True
            if static:
                self._write("/tf_static", "tf2_msgs/msg/TFMessage", rm.ros2_tf(static, t), t)
        self._write("/tf", "tf2_msgs/msg/TFMessage", rm.ros2_tf(dynamic, t), t)
        self._write("/odom", "nav_msgs/msg/Odometry",
                    rm.ros2_odometry(r.odometry.T_odom_base, r.odometry.twist_base, t, ODOM_FRAME,
                                     BASE_FRAME), t)
        js = r.joint_states
        self._write("/joint_states", "sensor_msgs/msg/JointState",
                    rm.ros2_joint_state(js.names, js.position, js.velocity, t), t)
        for cam in r.cameras:
            topics = camera_topics(cam.sensor_name)
            s = float(cam.stamp_s)
            self._write(topics["color"], "sensor_msgs/msg/Image",
                        rm.ros2_image(cam.color, s, cam.frame_id), s)
            self._write(topics["color_info"], "sensor_msgs/msg/CameraInfo",
                        rm.ros2_camera_info(cam.K, s, cam.frame_id), s)
            self._write(topics["depth"], "sensor_msgs/msg/Image",
                        rm.ros2_depth(cam.depth_m, s, cam.frame_id), s)
            self._write(topics["depth_info"], "sensor_msgs/msg/CameraInfo",
                        rm.ros2_camera_info(cam.K, s, cam.frame_id), s)
        self._path_stamps.append(t)
        self._path_poses.append(np.asarray(r.T_world_base, dtype=np.float64).copy())
        self._last_stamp_s = t
        self._steps += 1
        if self._steps % self.config.path_every_n_steps == 0:
            self._write_path()
