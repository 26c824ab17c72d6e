"""A small ``/rosout`` node (what Debian's C++ rosout does, bound to loopback; see :mod:`.master`).

Subscribes ``/rosout`` (rosgraph_msgs/Log from every node), republishes each message on
``/rosout_agg`` (what rqt_console reads) and appends one line per message to
``$ROS_HOME/log/rosout.log`` (restarted when it passes 50 MB). Run: ``python -m presim.outputs.ros.rosout``.
"""

from __future__ import annotations

import os
from pathlib import Path

from presim.outputs.ros.env import import_rospy

MAX_LOG_BYTES = 50 * 2**20
LEVELS = {1: "DEBUG", 2: "INFO", 4: "WARN", 8: "ERROR", 16: "FATAL"}


def main() -> int:
    rospy = import_rospy()
    from rosgraph_msgs.msg import Log

    rospy.init_node("rosout", anonymous=False, disable_rosout=True)
    home = Path(os.environ.get("ROS_HOME", Path.home() / ".ros"))
    log_dir = home / "log"
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / "rosout.log"
    f = open(path, "a", encoding="utf-8", errors="replace")
    agg = rospy.Publisher("/rosout_agg", Log, queue_size=100)

    def on_log(m):
        nonlocal f
        agg.publish(m)
        try:
            f.write(f"{m.header.stamp.to_sec():.6f} {LEVELS.get(m.level, m.level)} [{m.name}] {m.msg}\n")
            f.flush()
            if f.tell() > MAX_LOG_BYTES:
                f.close()
                f = open(path, "w", encoding="utf-8", errors="replace")
        except (OSError, ValueError):
            pass

    rospy.Subscriber("/rosout", Log, on_log, queue_size=100)
    try:
        rospy.spin()
    except KeyboardInterrupt:
        pass
    finally:
        f.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
