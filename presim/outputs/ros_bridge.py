"""Compatibility name for :mod:`presim.outputs.ros` (the ROS 1 bridge, split into named parts:
env, messages, commands, publisher, node, master, rosout). New code imports from there."""

from presim.outputs.ros.commands import CommandInbox, CommandLimits  # noqa: F401
from presim.outputs.ros.env import ROS_DIST_PACKAGES, import_rospy, ros_env  # noqa: F401
from presim.outputs.ros.master import RosCore, master_alive, start_roscore, stop_process_group  # noqa: F401
from presim.outputs.ros.messages import pose_to_T  # noqa: F401
from presim.outputs.ros.node import RosBridge, RosBridgeConfig  # noqa: F401
from presim.outputs.ros.publisher import RosPublisherSink  # noqa: F401

__all__ = ["ROS_DIST_PACKAGES", "import_rospy", "RosBridgeConfig", "RosPublisherSink", "CommandInbox",
           "CommandLimits", "RosBridge", "ros_env", "pose_to_T", "master_alive", "start_roscore",
           "stop_process_group", "RosCore"]
