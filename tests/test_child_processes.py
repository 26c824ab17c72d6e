"""Child processes end with presim (issue 44 item 8): a child started with
:func:`presim.procs.die_with_parent` is killed by the kernel when its parent is SIGKILLed; the ROS
master and ``/rosout`` that ``presim ros`` starts do not outlive a SIGKILLed parent; ``presim view
--web`` stops on the first Ctrl-C (SIGINT) and takes the rerun web viewer with it."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only")


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p),
                PRESIM_NO_PROGRESS="1")


def _gone(pid: int) -> bool:
    """Ended: no such process, or a zombie waiting for a reaper (a container's PID 1 may never reap)."""
    import psutil

    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_gone(pids, timeout_s: float = 5.0) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = [p for p in pids if not _gone(p)]
        if not alive:
            return []
        time.sleep(0.05)
    return [p for p in pids if not _gone(p)]


def _kill_leftovers(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.fuzz
def test_child_started_with_die_with_parent_ends_when_parent_is_sigkilled():
    code = ("import subprocess, sys, time\n"
            "from presim.procs import die_with_parent\n"
            "c = subprocess.Popen(['sleep', '60'], start_new_session=True, preexec_fn=die_with_parent())\n"
            "print(c.pid, flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=_env())
    child = int(parent.stdout.readline())
    try:
        assert not _gone(child)
        parent.kill()
        parent.wait()
        assert _wait_gone([child]) == []
    finally:
        _kill_leftovers([child])


def _ros_python() -> str | None:
    """An interpreter in which presim's /rosout node imports rospy: this one, or Debian's python3
    (a venv holding the ROS 2 message packages of the package index shadows ROS 1's
    ``rosgraph_msgs``); None when neither does."""
    probe = ("from presim.outputs.ros import import_rospy; import_rospy(); "
             "from rosgraph_msgs.msg import Log")
    for exe in (sys.executable, "/usr/bin/python3"):
        if os.path.exists(exe) and subprocess.run([exe, "-c", probe], env=_env(), capture_output=True,
                                                  timeout=60).returncode == 0:
            return exe
    return None


@pytest.mark.ros
@pytest.mark.fuzz
def test_sigkilled_parent_leaves_no_ros_master(tmp_path):
    """What ``presim ros`` does when no master runs (start_roscore), in a process that is then
    SIGKILLed: the master and /rosout end within 5 s and the master's port stops answering."""
    from presim.outputs.ros import master_alive, ros_env
    from presim.outputs.viewer import free_port

    python = _ros_python() if shutil.which("rosmaster") else None
    if python is None:
        if os.environ.get("CI") == "true":
            raise FileNotFoundError("rosmaster / rospy missing (scripts/setup.sh --test-system installs ROS 1)")
        pytest.skip("ROS 1 not installed (rosmaster or rospy missing)")
    port = free_port()
    env = ros_env(port, base={k: v for k, v in _env().items() if not k.startswith("ROS_")}
                  | {"ROS_HOME": str(tmp_path)})
    code = ("import os, sys, time\n"
            "from presim.outputs.ros import start_roscore\n"
            f"core = start_roscore({port}, dict(os.environ))\n"
            "print(core.master.pid, core.rosout.pid, flush=True)\n"
            "time.sleep(120)\n")
    parent = subprocess.Popen([python, "-c", code], stdout=subprocess.PIPE, text=True, env=env)
    pids = []
    try:
        line = parent.stdout.readline()
        assert line, "start_roscore failed in the child"
        pids = [int(v) for v in line.split()]
        uri = f"http://127.0.0.1:{port}"
        assert master_alive(uri)
        parent.kill()
        parent.wait()
        assert _wait_gone(pids) == [], "the ROS master / rosout outlived their SIGKILLed parent"
        assert not master_alive(uri, timeout_s=0.5)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        _kill_leftovers(pids)


@pytest.mark.fuzz
@pytest.mark.slow
def test_view_web_stops_on_first_ctrl_c(tmp_path):
    import psutil
    import rerun as rr

    rrd = tmp_path / "a.rrd"
    rec = rr.RecordingStream("presim-test")
    rec.save(str(rrd))
    rec.log("points", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    rec.flush()
    rec.disconnect()
    # its own process group, as a terminal's foreground job: Ctrl-C = SIGINT to the whole group
    p = subprocess.Popen([sys.executable, "-m", "presim", "view", str(rrd), "--web"], stderr=subprocess.PIPE,
                         stdout=subprocess.DEVNULL, text=True, env=_env(), start_new_session=True)
    children = []
    try:
        deadline = time.monotonic() + 60
        line = ""
        while "presim view: http" not in line and time.monotonic() < deadline:
            line = p.stderr.readline()
            if not line and p.poll() is not None:
                break
        assert "presim view: http" in line, f"no viewer URL (rc {p.poll()})"
        children = [c.pid for c in psutil.Process(p.pid).children(recursive=True)]
        assert children, "the web viewer process is missing"
        t0 = time.monotonic()
        os.killpg(p.pid, signal.SIGINT)                    # one Ctrl-C
        assert p.wait(10) == 130
        assert time.monotonic() - t0 < 5
        assert _wait_gone(children) == []
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        _kill_leftovers(children)
