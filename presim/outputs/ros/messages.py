"""rospy message building from sim values (the numbers come from :mod:`presim.outputs.ros_msgs`,
shared with the MCAP recorder). Every function takes the imported ``rospy`` module where it needs
``rospy.Time``; message classes are imported inside, since rospy is only importable after
:func:`~presim.outputs.ros.env.import_rospy`."""

from __future__ import annotations

import numpy as np

from presim.geometry import make_pose, quat_xyzw_to_R
from presim.outputs import ros_msgs as rm
from presim.outputs.frames import FrameEdge

__all__ = ["stamp", "header", "tf_msg", "pose_msg", "pose_to_T", "diagnostics_msg"]


def stamp(rospy, t_s: float):
    sec, nsec = rm.split_stamp(t_s)
    return rospy.Time(sec, nsec)


def header(rospy, t_s: float, frame_id: str):
    from std_msgs.msg import Header

    return Header(stamp=stamp(rospy, t_s), frame_id=frame_id)


def tf_msg(rospy, edges: list[FrameEdge], t_s: float):
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    from tf2_msgs.msg import TFMessage

    out = []
    for e in edges:
        (x, y, z), (qx, qy, qz, qw) = rm.pose_fields(e.T_parent_child)
        out.append(TransformStamped(header=header(rospy, t_s, e.parent), child_frame_id=e.child,
                                    transform=Transform(Vector3(x, y, z), Quaternion(qx, qy, qz, qw))))
    return TFMessage(transforms=out)


def pose_msg(T: np.ndarray):
    from geometry_msgs.msg import Point, Pose, Quaternion

    (x, y, z), (qx, qy, qz, qw) = rm.pose_fields(T)
    return Pose(Point(x, y, z), Quaternion(qx, qy, qz, qw))


def pose_to_T(pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 (no checks: validate with :func:`~presim.outputs.ros.commands.check_pose`)."""
    q = pose.orientation
    return make_pose(quat_xyzw_to_R(np.array([q.x, q.y, q.z, q.w])),
                     [pose.position.x, pose.position.y, pose.position.z])


def diagnostics_msg(rospy, t_s: float, node_name: str, counters: dict[str, int], last_drop: str,
                    new_drops: bool):
    """``diagnostic_msgs/DiagnosticArray`` with one status: the command counters. Level WARN when
    commands were dropped since the previous report, else OK."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    level = DiagnosticStatus.WARN if new_drops else DiagnosticStatus.OK
    message = f"dropped invalid commands: {last_drop}" if new_drops else "commands ok"
    values = [KeyValue(k, str(v)) for k, v in sorted(counters.items())]
    values.append(KeyValue("last_drop_reason", last_drop))
    status = DiagnosticStatus(level=level, name=f"{node_name}: commands", message=message,
                              hardware_id=node_name, values=values)
    return DiagnosticArray(header=header(rospy, t_s, ""), status=[status])
