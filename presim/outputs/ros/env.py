"""Where rospy comes from, and the loopback ROS environment.

rospy comes from Debian's packages (``ros-core``, ``python3-rospy``, message packages) installed in
``/usr/lib/python3/dist-packages``. The project's venv is not a ``--system-site-packages`` venv, so
:func:`import_rospy` APPENDS that folder to ``sys.path`` (at the end, so the venv's numpy, yaml etc.
win) before importing rospy. Both use Python 3.11, so the pure-Python ROS packages load as they are.
The one exception are ROS message packages (``*_msgs``, ``*_srvs``): the ``[ros2]`` group installs
ROS 2 packages of the same names (``sensor_msgs``, ``tf2_msgs``...) into the venv, so
:func:`import_rospy` loads Debian's ROS 1 ones by path first (:func:`_pin_ros1_message_packages`);
a process is either a ROS 1 or a ROS 2 node, never both.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import sys

__all__ = ["ROS_DIST_PACKAGES", "import_rospy", "ros_env", "evict_message_packages"]

ROS_DIST_PACKAGES = "/usr/lib/python3/dist-packages"


def evict_message_packages(keep_folder: str | None = None, drop_folder: str | None = None) -> list[str]:
    """Remove imported ROS message packages (``*_msgs``, ``*_srvs`` and their submodules) from
    ``sys.modules``: those NOT under ``keep_folder``, or those under ``drop_folder``. Only a process
    that imports both ROS flavours needs it (the test suite runs ``presim ros`` and ``presim ros2``
    in one interpreter); returns the evicted top-level names."""
    tops = {m.split(".")[0] for m in sys.modules if m.split(".")[0].endswith(("_msgs", "_srvs"))}
    evicted = []
    for top in sorted(tops):
        f = getattr(sys.modules.get(top), "__file__", None) or ""
        under_keep = keep_folder is not None and f.startswith(keep_folder + os.sep)
        under_drop = drop_folder is not None and f.startswith(drop_folder + os.sep)
        if (keep_folder is not None and not under_keep) or under_drop:
            for m in [m for m in sys.modules if m == top or m.startswith(top + ".")]:
                del sys.modules[m]
            evicted.append(top)
    return evicted


def _pin_ros1_message_packages(folder: str = ROS_DIST_PACKAGES) -> None:
    """Load every ROS 1 message package of ``folder`` (``*_msgs``, ``*_srvs``) from there, ahead of
    ROS 2 packages of the same name in the venv (ROS 2 ones already imported are evicted first)."""
    evict_message_packages(keep_folder=folder)
    for init in sorted(glob.glob(os.path.join(folder, "*_msgs", "__init__.py"))
                       + glob.glob(os.path.join(folder, "*_srvs", "__init__.py"))):
        name = os.path.basename(os.path.dirname(init))
        if name in sys.modules:
            continue
        spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[os.path.dirname(init)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        try:
            spec.loader.exec_module(mod)
        except Exception:
            del sys.modules[name]
            raise


def import_rospy():
    """Import Debian's rospy from the venv (see the module docstring). Clear error when missing."""
    if ROS_DIST_PACKAGES not in sys.path and os.path.isdir(ROS_DIST_PACKAGES):
        sys.path.append(ROS_DIST_PACKAGES)  # at the END: the venv's own packages keep priority
    try:
        if os.path.isdir(ROS_DIST_PACKAGES):
            _pin_ros1_message_packages()
        import rospy  # noqa: F401
    except ImportError as e:
        raise ImportError(f"rospy not found ({e}); install Debian's ROS 1 packages: "
                          "apt-get install ros-core python3-rospy ros-sensor-msgs ros-nav-msgs "
                          "ros-tf2-msgs ros-std-srvs python3-diagnostic-msgs "
                          "(scripts/setup.sh --test-system)") from e
    return rospy


def ros_env(master_port: int = 11311, host: str = "127.0.0.1", base: dict | None = None) -> dict[str, str]:
    """Environment for ROS processes on ``host`` (loopback by default: rospy then binds 127.0.0.1).

    Both ``ROS_IP`` and ``ROS_HOSTNAME`` are set: rospy's bind address follows whichever it reads
    (``ROS_IP`` first), and a node advertises ``ROS_HOSTNAME`` when set."""
    env = dict(os.environ if base is None else base)
    env.setdefault("ROS_MASTER_URI", f"http://{host}:{master_port}")
    env.setdefault("ROS_IP", host)
    env.setdefault("ROS_HOSTNAME", host)
    env.setdefault("ROS_HOME", os.path.join(os.path.expanduser("~"), ".ros"))
    return env
