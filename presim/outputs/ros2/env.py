"""Where rclpy comes from, the host-only discovery defaults, and the install line when it is missing.

rclpy and the message packages come from the package index (the ``[ros2]`` group: ``ros-rclpy``,
``ros-sensor-msgs``, ... ``ros-rmw-fastrtps-cpp``), installed into the project's venv. Their
``ros_wheels_bootstrapper.pth`` re-executes every Python of the venv once with ``LD_LIBRARY_PATH``
pointing at the wheels' libraries. ``tf2_msgs`` is not on the index: :mod:`.tf2_build` generates it
(``scripts/setup.sh`` runs it).

Discovery stays on this host: :func:`ros2_env` sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
unless the caller already chose a range (docs/ros2.md, "Opening discovery").
"""

from __future__ import annotations

import os

__all__ = ["INSTALL_LINE", "TF2_BUILD_LINE", "import_rclpy", "ros2_env", "LOCALHOST_ENV"]

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
