"""Where rclpy comes from, the host-only discovery defaults, and the install line when it is missing.

rclpy and the message packages come from the package index (the ``[ros2]`` group: ``ros-rclpy``,
``ros-sensor-msgs``, ... ``ros-rmw-fastrtps-cpp``), installed into the project's venv. Their
``ros_wheels_bootstrapper.pth`` re-executes every Python of the venv once with ``LD_LIBRARY_PATH``
pointing at the wheels' libraries. ``tf2_msgs`` is not on the index: :mod:`.tf2_build` generates it
(``scripts/setup.sh`` runs it).

Discovery stays on this host: :func:`ros2_env` sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
unless the caller already chose a range (docs/ros2.md, "Opening discovery").

The node's Fast DDS participant gets a profile (:func:`use_node_transport_profile`): a shared-memory
transport with a 16 MB segment, and UDPv4 receiving on 127.0.0.1 only while discovery is
host-only. Why: Fast DDS's default 512 KB shared-memory segment cannot carry a 640x480 frame
(0.9 MB color, 1.2 MB depth), so frames went over fragmented UDP, and a best-effort (sensor-data)
subscriber lost most of them on a loaded machine (measured 1.4-4 Hz of 10 Hz); with the larger
segment, written by the publisher, a stock subscriber received 10.0 Hz.
"""

from __future__ import annotations

import hashlib
import os
import tempfile

__all__ = ["INSTALL_LINE", "TF2_BUILD_LINE", "import_rclpy", "ros2_env", "LOCALHOST_ENV", "fastdds_profile",
           "use_node_transport_profile"]

INSTALL_LINE = "pip install -e '.[ros2]' && python -m presim.outputs.ros2.tf2_build  (or scripts/setup.sh)"
TF2_BUILD_LINE = "python -m presim.outputs.ros2.tf2_build  (scripts/setup.sh runs it)"

LOCALHOST_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
"""Environment that keeps DDS discovery on this host (ROS 2 Iron and later; Kilted wheels here)."""


def ros2_env(base: dict | None = None) -> dict[str, str]:
    """Environment for ROS 2 processes: host-only discovery unless ``ROS_AUTOMATIC_DISCOVERY_RANGE``
    (or the older ``ROS_LOCALHOST_ONLY``) is already set by the user."""
    env = dict(os.environ if base is None else base)
    if "ROS_AUTOMATIC_DISCOVERY_RANGE" not in env and "ROS_LOCALHOST_ONLY" not in env:
        env.update(LOCALHOST_ENV)
    return env


def import_rclpy():
    """Import rclpy and check that every message package the bridge uses is there; a clear error
    with the install line otherwise. Applies :func:`ros2_env`'s defaults to this process first."""
    for k, v in ros2_env().items():
        if k in LOCALHOST_ENV:
            os.environ.setdefault(k, v)
    from presim.outputs.ros.env import ROS_DIST_PACKAGES, evict_message_packages

    evict_message_packages(drop_folder=ROS_DIST_PACKAGES)  # ROS 1 ones, if this process loaded them
    try:
        import rclpy  # noqa: F401
        from diagnostic_msgs.msg import DiagnosticArray  # noqa: F401
        from geometry_msgs.msg import Twist  # noqa: F401
        from nav_msgs.msg import Odometry  # noqa: F401
        from rosgraph_msgs.msg import Clock  # noqa: F401
        from sensor_msgs.msg import Image  # noqa: F401
        from std_srvs.srv import Empty  # noqa: F401
    except ImportError as e:
        raise ImportError(f"ROS 2 (rclpy) not found ({e}): install the [ros2] group: {INSTALL_LINE}") from e
    if not hasattr(Image, "_TYPE_SUPPORT") and not hasattr(type(Image), "_TYPE_SUPPORT"):
        raise ImportError(f"sensor_msgs here is not a ROS 2 package ({Image.__module__}); install the "
                          f"[ros2] group: {INSTALL_LINE}")
    try:
        from tf2_msgs.msg import TFMessage

        if not hasattr(type(TFMessage), "_TYPE_SUPPORT"):
            raise ImportError(f"tf2_msgs at {TFMessage.__module__} is not a ROS 2 package")
    except ImportError as e:
        raise ImportError(f"tf2_msgs for ROS 2 not found ({e}); generate it: {TF2_BUILD_LINE}") from e
    return rclpy


SHM_SEGMENT_BYTES = 16 * 1024 * 1024
"""Fast DDS shared-memory segment of the node: several 640x480 RGB-D frames (2.1 MB each) in flight."""


def fastdds_profile(localhost_only: bool) -> str:
    """Fast DDS XML: shared memory (``SHM_SEGMENT_BYTES``) + UDPv4 (receiving on 127.0.0.1 only when
    ``localhost_only``) as the default participant profile."""
    allow = "\n        <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>" if localhost_only else ""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>presim_shm</transport_id>
        <type>SHM</type>
        <segment_size>{SHM_SEGMENT_BYTES}</segment_size>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>presim_udp</transport_id>
        <type>UDPv4</type>{allow}
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="presim_node" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>presim_shm</transport_id>
          <transport_id>presim_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def use_node_transport_profile() -> str | None:
    """Point this process's Fast DDS at :func:`fastdds_profile` (before ``rclpy.init``), unless the
    user set ``FASTDDS_DEFAULT_PROFILES_FILE`` or chose another middleware. Returns the file used."""
    if os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE") or os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
        return None
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    rng = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST").upper()
    text = fastdds_profile(localhost_only=rng in ("LOCALHOST", "OFF"))
    name = f"presim-fastdds-{os.getuid()}-{hashlib.sha256(text.encode()).hexdigest()[:12]}.xml"
    path = os.path.join(tempfile.gettempdir(), name)
    if not os.path.isfile(path):
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, path)  # atomic: a concurrent node never reads half a file
    os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = path
    return path
