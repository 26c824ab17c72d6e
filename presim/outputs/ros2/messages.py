"""rclpy messages filled from :mod:`presim.outputs.ros_msgs`'s ROS 2 dicts (the content the MCAP
recorder writes, so the live topics and the recordings cannot drift apart), and the QoS profiles.

Message classes are imported inside the functions: rclpy is only importable after
:func:`~presim.outputs.ros2.env.import_rclpy`.
"""

from __future__ import annotations

import importlib
from functools import lru_cache

__all__ = ["fill", "make", "qos_profiles", "diagnostics_msg"]


@lru_cache(maxsize=None)
def _field_types(cls) -> dict[str, str]:
    return dict(cls.get_fields_and_field_types())


@lru_cache(maxsize=None)
def _element_class(type_str: str):
    """``'sequence<geometry_msgs/TransformStamped>'`` -> the message class (None for primitives)."""
    inner = type_str.split("<", 1)[1].rsplit(">", 1)[0].split(",")[0] if "<" in type_str else type_str
    inner = inner.split("[")[0]
    if "/" not in inner:
        return None
    pkg, name = inner.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def fill(msg, values: dict):
    """Set the fields of an rclpy message from a ``ros_msgs.ros2_*`` dict (nested dicts become nested
    messages, lists of dicts sequences of messages; bytes go to ``uint8[]`` unchanged). Returns ``msg``."""
    types = _field_types(type(msg))
    for k, v in values.items():
        if isinstance(v, dict):
            fill(getattr(msg, k), v)
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            cls = _element_class(types[k])
            setattr(msg, k, [fill(cls(), e) for e in v])
        else:
            setattr(msg, k, v)
    return msg


def make(cls, values: dict):
    """A new ``cls`` message filled from ``values``."""
    return fill(cls(), values)


def qos_profiles() -> dict[str, object]:
    """The QoS profiles of the bridge (docs/ros2.md, "Topics and QoS").

    - ``sensor``: rclpy's sensor-data profile (best effort, keep last 5, volatile): camera topics;
    - ``reliable_sensor``: the same, reliable: the ``/<camera>/reliable/...`` variants that RViz2's
      default (reliable) subscriptions match;
    - ``default``: reliable, keep last 10, volatile (odom, path, joint_states, clock, diagnostics);
    - ``tf``: reliable, keep last 100, volatile (tf2_ros's dynamic broadcaster profile);
    - ``latched``: reliable, keep last 1, transient local (``/tf_static``, ``/map_cloud``,
      ``/robot_description``: late subscribers get the last message);
    - ``command``: best effort, keep last 10: inputs; a best-effort subscription matches reliable and
      best-effort publishers; during a flood the middleware overwrites all but the newest 10 (with
      keep last 1, commands sent 30 ms apart were lost unread at load 9 on 2 cores, so the
      /diagnostics counts missed them).
    """
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                           qos_profile_sensor_data)

    def p(depth, rel, dur=DurabilityPolicy.VOLATILE):
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel, durability=dur)

    R, BE = ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT
    return {"sensor": qos_profile_sensor_data, "reliable_sensor": p(5, R), "default": p(10, R),
            "tf": p(100, R), "latched": p(1, R, DurabilityPolicy.TRANSIENT_LOCAL), "command": p(10, BE)}


def diagnostics_msg(stamp_s: float, node_name: str, counters: dict[str, int], last_drop: str, new_drops: bool):
    """``diagnostic_msgs/DiagnosticArray`` with one status: the command counters (the same keys as
    the ROS 1 bridge). Level WARN when commands were dropped since the previous report, else OK."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from presim.outputs import ros_msgs as rm

    st = DiagnosticStatus()
    st.level = DiagnosticStatus.WARN if new_drops else DiagnosticStatus.OK
    st.name = f"{node_name}: commands"
    st.message = f"dropped invalid commands: {last_drop}" if new_drops else "commands ok"
    st.hardware_id = node_name
    st.values = ([KeyValue(key=k, value=str(v)) for k, v in sorted(counters.items())]
                 + [KeyValue(key="last_drop_reason", value=last_drop)])
    arr = DiagnosticArray()
    fill(arr.header, rm.ros2_header(stamp_s, ""))
    arr.status = [st]
    return arr
