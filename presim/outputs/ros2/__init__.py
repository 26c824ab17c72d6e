"""ROS 2 bridge: the simulator as a ROS 2 node (rclpy from the package index). Topics, QoS, frames,
services, invalid-input handling and discovery: docs/ros2.md.

- :mod:`.env`: where rclpy comes from (:func:`import_rclpy`, the install line when missing) and the
  host-only discovery defaults (:func:`ros2_env`);
- :mod:`.tf2_build`: generates the ``tf2_msgs`` package (not on the index) at set-up;
- :mod:`.messages`: rclpy messages filled from :mod:`presim.outputs.ros_msgs`'s ROS 2 dicts (the
  same content as the MCAP recorder), QoS profiles;
- :mod:`.publisher`: :class:`Ros2PublisherSink`, a simulator sink publishing every step;
- :mod:`.node`: :class:`Ros2Bridge` (subscribers, services, ``/diagnostics``; the paced step loop,
  command validation and request handling are the ROS 1 bridge's);
- :mod:`.probe`: a client process used by the tests (rates, tf, commands, fuzz).

Names are imported lazily, so importing the package does not import rclpy.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "import_rclpy": "env", "ros2_env": "env", "INSTALL_LINE": "env",
    "build_tf2_msgs": "tf2_build",
    "Ros2PublisherSink": "publisher",
    "Ros2Bridge": "node", "Ros2BridgeConfig": "node",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
