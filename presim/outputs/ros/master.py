"""The ROS master and ``/rosout`` processes that ``presim ros`` starts when none runs.

Why not ``roscore``: Debian's ``roscore`` starts ``rosmaster`` (Python: binds its XML-RPC server to
127.0.0.1 when ``ROS_IP``/``ROS_HOSTNAME`` is a loopback address, through
``rosgraph.network.get_bind_address``) and the C++ ``rosout`` node. roscpp binds rosout's TCPROS
server to loopback too, but its XML-RPC server (XmlRpc++) always binds ``INADDR_ANY``: measured,
``rosout`` listened on ``0.0.0.0:<random port>`` with ``ROS_IP=ROS_HOSTNAME=127.0.0.1`` set, and no
environment variable changes that. So :func:`start_roscore` starts ``rosmaster --core`` itself and
replaces the C++ rosout with :mod:`presim.outputs.ros.rosout`, a rospy node doing rosout's job
(``/rosout`` → ``/rosout_agg`` and a log file), which binds where rospy binds: 127.0.0.1.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

from presim.procs import die_with_parent

__all__ = ["master_alive", "start_roscore", "stop_process_group", "RosCore"]


def master_alive(uri: str, timeout_s: float = 1.0) -> bool:
    """True when a ROS master answers at ``uri`` (XML-RPC getPid)."""
    import socket
    import xmlrpc.client

    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout_s)
    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).getPid("/presim_check")
        return code == 1
    except (OSError, xmlrpc.client.Error):
        return False
    finally:
        socket.setdefaulttimeout(old)


def _node_registered(uri: str, node: str) -> bool:
    import xmlrpc.client

    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).lookupNode("/presim_check", node)
        return code == 1
    except (OSError, xmlrpc.client.Error):
        return False


class RosCore:
    """``rosmaster`` and the loopback ``/rosout`` node, each leading its own process group.

    Quacks like the master's ``Popen`` (``pid``, ``poll``, ``wait``, ``returncode``);
    :func:`stop_process_group` stops both groups (rosout first)."""

    def __init__(self, master: subprocess.Popen, rosout: subprocess.Popen | None = None):
        self.master, self.rosout = master, rosout

    @property
    def pid(self) -> int:
        return self.master.pid

    @property
    def returncode(self):
        return self.master.returncode

    def poll(self):
        if self.rosout is not None:
            self.rosout.poll()
        return self.master.poll()

    def wait(self, timeout: float | None = None):
        end = None if timeout is None else time.monotonic() + timeout
        rc = self.master.wait(timeout)
        if self.rosout is not None:
            self.rosout.wait(None if end is None else max(0.1, end - time.monotonic()))
        return rc


def _which(name: str) -> str:
    exe = shutil.which(name)
    if exe is None:
        raise FileNotFoundError(f"{name} not found: install Debian's ros-core (scripts/setup.sh --test-system)")
    return exe


def start_roscore(port: int, env: dict[str, str], timeout_s: float = 30.0, log=None) -> RosCore:
    """Start a ROS master on ``port`` plus the loopback ``/rosout`` node (see the module docstring),
    each in a new process group; returns once both answer. Stop it with :func:`stop_process_group`.
    Both get SIGKILL from the kernel if this process dies first (:func:`presim.procs.die_with_parent`):
    a killed ``presim ros`` leaves no master behind.

    ``env`` should carry ``ROS_IP``/``ROS_HOSTNAME`` (:func:`~presim.outputs.ros.env.ros_env`):
    everything then binds to that address (127.0.0.1 by default)."""
    import xmlrpc.client

    out = log or subprocess.DEVNULL
    master = subprocess.Popen([_which("rosmaster"), "--core", "-p", str(port), "-w", "3"], env=env,
                              stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                              start_new_session=True, preexec_fn=die_with_parent())
    core = RosCore(master)
    host = env.get("ROS_HOSTNAME") or env.get("ROS_IP") or "127.0.0.1"
    uri = f"http://{host}:{port}"
    try:
        deadline = time.monotonic() + timeout_s
        while not master_alive(uri):
            if master.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ROS master on port {port} did not come up (exit code {master.poll()})")
            time.sleep(0.2)
        proxy = xmlrpc.client.ServerProxy(uri)
        proxy.setParam("/presim", "/run_id", str(uuid.uuid1()))
        proxy.setParam("/presim", "/rosdistro", "debian")
        proxy.setParam("/presim", "/rosversion", "1")
        child_env = dict(env, ROS_MASTER_URI=uri)
        pkg_root = str(Path(__file__).resolve().parents[3])  # so the child imports this presim
        child_env["PYTHONPATH"] = os.pathsep.join(p for p in (pkg_root, env.get("PYTHONPATH", "")) if p)
        core.rosout = subprocess.Popen([sys.executable, "-m", "presim.outputs.ros.rosout"], env=child_env,
                                       stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                       start_new_session=True, preexec_fn=die_with_parent())
        while not _node_registered(uri, "/rosout"):
            if core.rosout.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"/rosout node did not come up (exit code {core.rosout.poll()})")
            time.sleep(0.2)
    except BaseException:
        stop_process_group(core)
        raise
    return core


def stop_process_group(p, timeout_s: float = 10.0) -> None:
    """SIGINT then SIGKILL the process group led by ``p`` (a process we started with start_new_session)."""
    if isinstance(p, RosCore):
        stop_process_group(p.rosout, timeout_s)
        stop_process_group(p.master, timeout_s)
        return
    if p is None or p.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue
