"""ROS message content built from sim outputs, independent of the transport.

Two flavours share the same numbers:

- ROS 2 (MCAP recordings): the official ROS 2 Humble ``.msg`` definitions (comments stripped) in
  the concatenated form ``ros2 bag record`` stores as an MCAP schema, and builders returning plain
  dicts that ``mcap_ros2``'s CDR encoder serialises.
- ROS 1 (live bridge): :mod:`presim.outputs.ros` (messages.py, publisher.py) fills rospy message classes from the same
  helpers (:func:`image_fields`, :func:`camera_info_fields`, :func:`pose_fields`, :func:`cloud_fields`).
- ROS 2 (live bridge): :mod:`presim.outputs.ros2` fills rclpy messages from the ROS 2 dicts below
  (:func:`presim.outputs.ros2.messages.fill`), so its topics carry exactly what the recordings hold.

Encodings (documented in docs/ros.md): color ``rgb8``; depth ``32FC1`` metres registered to the color
camera, invalid pixels NaN (REP-118; in memory they are 0); CameraInfo ``plumb_bob`` with zero
distortion (sim images are undistorted); point cloud ``x y z rgb`` float32 (PCL's packed rgb).
"""

from __future__ import annotations

import numpy as np

from presim.geometry import Intrinsics, R_to_quat_xyzw
from presim.outputs.frames import FrameEdge

__all__ = ["MSGDEFS", "msgdef", "split_stamp", "image_fields", "depth_to_ros", "camera_info_fields",
           "pose_fields", "cloud_fields", "ros2_header", "ros2_clock", "ros2_image", "ros2_depth", "ros2_camera_info",
           "ros2_tf", "ros2_odometry", "ros2_path", "ros2_joint_state", "ros2_point_cloud"]

_SEP = "=" * 80 + "\n"

# Leaf definitions (ROS 2 Humble, comments stripped; field order is the wire order).
_DEFS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/String": "string data\n",
    "rosgraph_msgs/Clock": "builtin_interfaces/Time clock\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                          "uint8 is_bigendian\nuint32 step\nuint8[] data\n"),
    "sensor_msgs/RegionOfInterest": ("uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
                                     "bool do_rectify\n"),
    "sensor_msgs/CameraInfo": ("std_msgs/Header header\nuint32 height\nuint32 width\n"
                               "string distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\n"
                               "float64[12] p\nuint32 binning_x\nuint32 binning_y\n"
                               "sensor_msgs/RegionOfInterest roi\n"),
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/TransformStamped": ("std_msgs/Header header\nstring child_frame_id\n"
                                       "geometry_msgs/Transform transform\n"),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "nav_msgs/Odometry": ("std_msgs/Header header\nstring child_frame_id\n"
                          "geometry_msgs/PoseWithCovariance pose\n"
                          "geometry_msgs/TwistWithCovariance twist\n"),
    "nav_msgs/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    "sensor_msgs/JointState": ("std_msgs/Header header\nstring[] name\nfloat64[] position\n"
                               "float64[] velocity\nfloat64[] effort\n"),
    "sensor_msgs/PointField": ("uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
                               "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
                               "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"),
    "sensor_msgs/PointCloud2": ("std_msgs/Header header\nuint32 height\nuint32 width\n"
                                "sensor_msgs/PointField[] fields\nbool is_bigendian\n"
                                "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"),
}


def _deps(name: str, seen: list[str]) -> list[str]:
    for line in _DEFS[name].splitlines():
        ftype = line.split()[0].split("[")[0]
        if "/" in ftype and ftype not in seen:
            seen.append(ftype)
            _deps(ftype, seen)
    return seen


def msgdef(ros2_type: str) -> str:
    """Concatenated ROS 2 message definition of ``pkg/msg/Name`` (the MCAP ``ros2msg`` schema)."""
    pkg, _, name = ros2_type.split("/")
    short = f"{pkg}/{name}"
    if short not in _DEFS:
        raise ValueError(f"no message definition for {ros2_type!r}")
    text = _DEFS[short]
    for dep in _deps(short, []):
        text += _SEP + f"MSG: {dep}\n" + _DEFS[dep]
    return text


MSGDEFS = {t: msgdef(t) for t in (
    "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "tf2_msgs/msg/TFMessage",
    "nav_msgs/msg/Odometry", "nav_msgs/msg/Path", "sensor_msgs/msg/JointState",
    "sensor_msgs/msg/PointCloud2", "std_msgs/msg/String", "rosgraph_msgs/msg/Clock")}


# ---- transport-neutral field values ---------------------------------------------------------------

def split_stamp(stamp_s: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec) with 0 <= nanosec < 1e9."""
    ns = int(round(float(stamp_s) * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def image_fields(color: np.ndarray) -> dict:
    """rgb8 Image fields (height, width, encoding, step, data bytes) of a uint8 (H, W, 3) image."""
    color = np.ascontiguousarray(color)
    if color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] != 3:
        raise ValueError(f"color image must be uint8 (H, W, 3), got {color.dtype} {color.shape}")
    h, w = color.shape[:2]
    return {"height": h, "width": w, "encoding": "rgb8", "is_bigendian": 0, "step": 3 * w,
            "data": color.tobytes()}


def depth_to_ros(depth_m: np.ndarray) -> np.ndarray:
    """float32 (H, W) metres with 0 = invalid -> REP-118 depth (invalid = NaN), little-endian."""
    d = np.asarray(depth_m, dtype="<f4")
    # Border conversion: our 0 = invalid becomes REP-118's NaN.
    return np.where(d > 0, d, np.float32(np.nan)).astype("<f4", copy=False)


def depth_fields(depth_m: np.ndarray) -> dict:
    d = np.asarray(depth_m)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    h, w = d.shape
    return {"height": h, "width": w, "encoding": "32FC1", "is_bigendian": 0, "step": 4 * w,
            "data": depth_to_ros(d).tobytes()}


def camera_info_fields(K: Intrinsics) -> dict:
    """CameraInfo numbers of an undistorted pinhole camera (k, r, p row-major, plumb_bob, d = 0)."""
    k = [K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0]
    p = [K.fx, 0.0, K.cx, 0.0, 0.0, K.fy, K.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return {"height": K.height, "width": K.width, "distortion_model": "plumb_bob",
            "d": [0.0] * 5, "k": k, "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "p": p}


def pose_fields(T: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """4x4 pose -> ((x, y, z), (qx, qy, qz, qw))."""
    T = np.asarray(T, dtype=np.float64)
    q = R_to_quat_xyzw(T[:3, :3])
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), tuple(float(v) for v in q)


def cloud_fields(points_xyz: np.ndarray, points_rgb: np.ndarray) -> dict:
    """PointCloud2 numbers: fields x, y, z (float32) and rgb (PCL packed 0x00RRGGBB in a float32)."""
    xyz = np.asarray(points_xyz, dtype=np.float32)
    rgb = np.asarray(points_rgb, dtype=np.uint8)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"point cloud must be (M, 3) xyz and (M, 3) rgb, got {xyz.shape} {rgb.shape}")
    buf = np.zeros((len(xyz), 4), dtype="<f4")
    buf[:, :3] = xyz
    packed = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    buf.view("<u4")[:, 3] = packed
    fields = [{"name": n, "offset": o, "datatype": 7, "count": 1}
              for n, o in (("x", 0), ("y", 4), ("z", 8), ("rgb", 12))]
    return {"height": 1, "width": len(xyz), "fields": fields, "is_bigendian": False,
            "point_step": 16, "row_step": 16 * len(xyz), "data": buf.tobytes(), "is_dense": True}


# ---- ROS 2 dicts (mcap_ros2 encoder input) -------------------------------------------------------

def ros2_header(stamp_s: float, frame_id: str) -> dict:
    sec, nsec = split_stamp(stamp_s)
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame_id}


def ros2_clock(stamp_s: float) -> dict:
    sec, nsec = split_stamp(stamp_s)
    return {"clock": {"sec": sec, "nanosec": nsec}}


def ros2_image(color: np.ndarray, stamp_s: float, frame_id: str) -> dict:
    return {"header": ros2_header(stamp_s, frame_id), **image_fields(color)}


def ros2_depth(depth_m: np.ndarray, stamp_s: float, frame_id: str) -> dict:
    return {"header": ros2_header(stamp_s, frame_id), **depth_fields(depth_m)}


def ros2_camera_info(K: Intrinsics, stamp_s: float, frame_id: str) -> dict:
    return {"header": ros2_header(stamp_s, frame_id), **camera_info_fields(K), "binning_x": 0,
            "binning_y": 0, "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0,
                                    "do_rectify": False}}


def _ros2_pose(T: np.ndarray) -> dict:
    (x, y, z), (qx, qy, qz, qw) = pose_fields(T)
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def ros2_tf(edges: list[FrameEdge], stamp_s: float) -> dict:
    out = []
    for e in edges:
        (x, y, z), (qx, qy, qz, qw) = pose_fields(e.T_parent_child)
        out.append({"header": ros2_header(stamp_s, e.parent), "child_frame_id": e.child,
                    "transform": {"translation": {"x": x, "y": y, "z": z},
                                  "rotation": {"x": qx, "y": qy, "z": qz, "w": qw}}})
    return {"transforms": out}


def ros2_odometry(T_odom_base: np.ndarray, twist_base: np.ndarray, stamp_s: float,
                  odom_frame: str, base_frame: str) -> dict:
    tw = np.asarray(twist_base, dtype=np.float64).reshape(6)
    return {"header": ros2_header(stamp_s, odom_frame), "child_frame_id": base_frame,
            "pose": {"pose": _ros2_pose(T_odom_base), "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": {"x": tw[0], "y": tw[1], "z": tw[2]},
                                "angular": {"x": tw[3], "y": tw[4], "z": tw[5]}},
                      "covariance": [0.0] * 36}}


def ros2_path(stamps_s: list[float], T_world_bases: list[np.ndarray], frame_id: str) -> dict:
    poses = [{"header": ros2_header(s, frame_id), "pose": _ros2_pose(T)}
             for s, T in zip(stamps_s, T_world_bases)]
    return {"header": ros2_header(stamps_s[-1] if stamps_s else 0.0, frame_id), "poses": poses}


def ros2_joint_state(names: tuple[str, ...], position: np.ndarray, velocity: np.ndarray,
                     stamp_s: float) -> dict:
    return {"header": ros2_header(stamp_s, ""), "name": list(names),
            "position": [float(v) for v in np.asarray(position).ravel()],
            "velocity": [float(v) for v in np.asarray(velocity).ravel()], "effort": []}


def ros2_point_cloud(points_xyz: np.ndarray, points_rgb: np.ndarray, stamp_s: float,
                     frame_id: str) -> dict:
    return {"header": ros2_header(stamp_s, frame_id), **cloud_fields(points_xyz, points_rgb)}
