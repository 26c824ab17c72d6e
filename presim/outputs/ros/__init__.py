"""ROS 1 bridge: the simulator as a ROS node (thesis §2.3, §4.3.1, §4.3.4). Topics, frames, services,
invalid-input handling and bind addresses: docs/ros.md.

One module per job, so a reader can name each part:

- :mod:`.env`: where rospy comes from (:func:`import_rospy`) and the loopback ROS environment
  (:func:`ros_env`);
- :mod:`.messages`: rospy message building (stamps, headers, tf, poses, diagnostics);
- :mod:`.commands`: command validation (pure functions) and the :class:`CommandInbox` the ROS
  callbacks write and the step loop reads, with accepted/dropped counters;
- :mod:`.publisher`: :class:`RosPublisherSink`, a simulator sink publishing every step;
- :mod:`.node`: :class:`RosBridge` (node set-up, subscribers, services, the paced step loop,
  ``/diagnostics``) and :class:`RosBridgeConfig`;
- :mod:`.master`: the ROS master and ``/rosout`` processes (:func:`start_roscore`, loopback only),
  :func:`master_alive`, :func:`stop_process_group`;
- :mod:`.rosout`: a small loopback ``/rosout`` aggregator node run by :func:`start_roscore`.

Names are imported lazily (``from presim.outputs.ros import RosBridge`` works) so that starting the
rosout node does not import the simulator.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "ROS_DIST_PACKAGES": "env", "import_rospy": "env", "ros_env": "env",
    "pose_to_T": "messages",
    "CommandInbox": "commands", "CommandLimits": "commands", "check_twist": "commands",
    "check_joint_command": "commands", "check_pose": "commands",
    "RosPublisherSink": "publisher",
    "RosBridge": "node", "RosBridgeConfig": "config",
    "master_alive": "master", "start_roscore": "master", "stop_process_group": "master",
    "RosCore": "master",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
