"""``presim ros2`` end to end: the node runs as a subprocess on the sample scene, and a separate rclpy
process (``presim.outputs.ros2.probe``, stock QoS, no PreSim transport settings) checks what a ROS 2
user sees: images, camera_info, /clock, /odom, the tf tree, QoS, /presim/teleport, invalid commands
dropped and counted on /diagnostics, /cmd_vel moving the base, a 1 kHz /cmd_vel soak, and clean
shutdown on SIGTERM / SIGINT / --max-steps with complete recordings.

Every test runs on its own random ROS_DOMAIN_ID, so parallel runs on one host do not see each other.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="needs the [ros2] group (scripts/setup.sh)")

ROOT = Path(__file__).resolve().parents[1]
START = (-1.5, 1.0, 0.0)  # free floor in the sample room, facing +x with 1 m of free floor ahead


def _env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PRESIM_NO_PROGRESS"] = "1"
    return env


def _start_node(scene: Path, domain_id: int, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "presim", "ros2", str(scene), *args], env=_env(domain_id),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def _probe(domain_id: int, *args: str, timeout_s: float = 120) -> dict:
    r = subprocess.run([sys.executable, "-m", "presim.outputs.ros2.probe", *args], env=_env(domain_id),
                       capture_output=True, text=True, timeout=timeout_s)
    assert r.returncode == 0, f"probe failed ({r.returncode}): {r.stdout[-2000:]} {r.stderr[-2000:]}"
    return json.loads(r.stdout.strip().splitlines()[-1])


def _stop(p: subprocess.Popen, sig=signal.SIGINT, timeout_s: float = 30) -> tuple[int, str]:
    if p.poll() is None:
        p.send_signal(sig)
    try:
        _, err = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        _, err = p.communicate()
        pytest.fail(f"node did not stop within {timeout_s} s after {sig!r}: {err[-2000:]}")
    return p.returncode, err


@pytest.fixture(scope="module")
def sample_scene(tmp_path_factory) -> Path:
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    return build_sample_scene(tmp_path_factory.mktemp("ros2") / "sample", seed=0,
                              config=SampleSceneConfig(width=320, height=240, num_frames=16))


@pytest.fixture(scope="module")
def node(sample_scene):
    """``presim ros2`` on the sample scene at 640x480, 10 Hz (one node for the module's checks)."""
    import psutil

    domain_id = random.randint(1, 100)
    p = _start_node(sample_scene, domain_id, "--width", "640", "--height", "480", "--rate-hz", "10")
    proc, end = psutil.Process(p.pid), time.monotonic() + 120
    while p.poll() is None and time.monotonic() < end and not proc.net_connections(kind="udp"):
        time.sleep(0.2)  # until its DDS participant exists (the scene is loaded by then)
    assert p.poll() is None, p.communicate()[1][-2000:]
    yield p, domain_id
    rc, err = _stop(p)
    assert rc == 130, err[-2000:]


@pytest.mark.slow
def test_ros2_end_to_end_images_tf_commands(node):
    p, domain_id = node
    r = _probe(domain_id, "e2e", "--start", *map(str, START), "--listen-s", "4")
    assert p.poll() is None, "node died"
    print(f"e2e: node {r['node_step_rate_hz']:.2f} steps/s, color {r['color_rate_hz']:.2f} Hz, "
          f"depth {r['depth_rate_hz']:.2f} Hz (published {r['color_published_hz']:.2f}, "
          f"{r['depth_published_hz']:.2f} Hz, "
          f"longest pause {r['color_pause_s_max']:.2f} s; lost {r['color_lost']}, {r['depth_lost']}; waited at most "
          f"{r['color_wait_ms_max']:.0f}, {r['depth_wait_ms_max']:.0f} ms), drive {r['drive_distance_m']:.3f} m "
          f"in {r['drive_sim_s']:.2f} s sim, diagnostics {r['diagnostics']}")
    # what a stock subscriber gets: the first and the last image deserialized, and every image received
    # in the window of one serialized size (the same layout)
    for key, enc, px in (("color", "rgb8", 3), ("depth", "32FC1", 4)):
        assert r[key] == r[f"{key}_first"] == [640, 480, enc, 640 * 480 * px], r
        assert len(r[f"{key}_sizes"]) == 1 and r[f"{key}_sizes"][0] > 640 * 480 * px, r
    w, h, model, k = r["camera_info"]
    assert (w, h, model) == (640, 480, "plumb_bob") and k[2] == pytest.approx(319.5) and k[8] == 1.0
    assert r["clock_n"] > 0 and r["odom_n"] > 0
    edges = {tuple(e) for e in r["tf_edges"]}
    assert {("map", "odom"), ("odom", "base_link")} <= edges
    assert ("camera_link", "camera_optical_frame") in {tuple(e) for e in r["static_edges"]}
    # The node publishes a frame per step; this separate process (best effort, sensor-data QoS) receives
    # them at >= 9 Hz (the bound at --rate-hz 10), and what the node published in the window (its
    # sequence numbers over its source timestamps) with at most one frame lost. With rclpy's
    # MultiThreadedExecutor in the node, 1 run in 3-8 paused 0.3-1.0 s here (5.7-9.0 Hz; docs/ros2.md).
    assert r["node_step_rate_hz"] >= 9.0, r
    for key in ("color", "depth"):
        assert r[f"{key}_lost"] <= 1 and r[f"{key}_rate_hz"] >= 0.95 * r[f"{key}_published_hz"], r
        assert r[f"{key}_rate_hz"] >= 9.0, r
    # QoS: sensor data (best effort) + reliable variant; latched topics transient local
    q = r["qos"]
    assert q["/head_camera/color/image_raw"] == ["best_effort", "volatile"]
    assert q["/head_camera/reliable/color/image_raw"] == ["reliable", "volatile"]
    for t in ("/tf_static", "/map_cloud", "/robot_description"):
        assert q[t] == ["reliable", "transient_local"], t
    assert q["/tf"] == ["reliable", "volatile"]
    # the teleport service, then invalid commands: dropped, counted, the base still, the node alive
    assert r["teleport_ok"] is True
    d = {k: (int(v) if v.isdigit() else v) for k, v in r["diagnostics"].items()}
    sent = r["bad_sent"]
    # Inputs are best effort (docs/ros2.md): under load some bad messages never reach the node, so the
    # test asks that none was accepted and that drops were counted (2 of 7 arrived once in the full suite).
    for topic in ("cmd_vel", "joint_command", "initialpose"):
        assert d[f"{topic}_accepted"] == 0 and 1 <= d[f"{topic}_dropped"] <= sent[topic], (topic, d)
    assert d["step_errors"] == 0 and d["last_drop_reason"]
    assert r["moved_by_bad_m"] < 1e-3 and r["images_after_bad"] > 0
    # /cmd_vel 0.3 m/s: distance = v x (commanded sim time + the tail until the 0.5 s wall-clock command
    # timeout), less the acceleration ramps; the tail is shorter in sim time when the node runs behind
    lo, hi = r["drive_speed"] * r["drive_sim_s"], r["drive_speed"] * (r["drive_sim_s"] + 0.5)
    assert lo - 0.15 < r["drive_distance_m"] < hi + 0.15, r
    assert r["reset_ok"] and r["clock_after_reset_increased"], r


@pytest.mark.slow
def test_ros2_node_receives_on_loopback_only(node):
    """Host-only by default: every socket the node can be reached on (the RTPS locators: fixed ports
    below the ephemeral range) is bound to 127.0.0.1, and nothing listens on TCP elsewhere. Fast DDS's
    send sockets sit on ephemeral ports and are never read."""
    import psutil

    p, _ = node
    lo_eph = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    conns = psutil.Process(p.pid).net_connections(kind="inet")
    fixed = [c.laddr for c in conns if c.type == 2 and c.laddr.port < lo_eph]  # SOCK_DGRAM
    assert fixed and all(a.ip == "127.0.0.1" for a in fixed), fixed
    listening = [c.laddr for c in conns if c.status == psutil.CONN_LISTEN]
    assert all(a.ip in ("127.0.0.1", "::1") for a in listening), listening


@pytest.mark.fuzz
def test_ros2_cmd_vel_soak_1khz_keeps_rate_and_memory(node):
    import psutil

    p, domain_id = node
    proc = psutil.Process(p.pid)
    _probe(domain_id, "soak", "--hz", "1000", "--seconds", "1", "--before-s", "0")  # warm-up: the node has served a client
    rss0 = proc.memory_info().rss
    r = _probe(domain_id, "soak", "--hz", "1000", "--seconds", "10")
    rss1 = proc.memory_info().rss
    assert p.poll() is None
    print(f"soak: {r['sent']} msgs in {r['seconds']:.1f} s ({r['send_hz']:.0f} Hz), images {r['color_rate_hz']:.1f} Hz "
          f"(published {r['color_published_hz']:.1f} Hz, lost {r['color_lost']}; node {r['node_step_rate_hz']:.1f} steps/s; "
          f"before: {r['before_color_rate_hz']:.1f}, "
          f"{r['before_node_step_rate_hz']:.1f}), "
          f"RSS {rss0 / 2**20:.1f} -> {rss1 / 2**20:.1f} MiB")
    assert r["sent"] >= 6500, r  # the sender shares 2 cores with the node
    # The flood does not slow the node (its loop takes at most 20 waiting commands per step, docs/ros2.md):
    # its step rate holds its rate of the 3 s before the flood, and the probe receives the images it publishes
    # (other work on the 2 cores moves both; 0.4-1.3 Hz in the flood when the executor ran a callback per
    # command). Both are measured against the node's own clock: the probe's arrival rate over a few seconds
    # is not, since frames arrive bunched (17.5 Hz "received" in a 3 s window of a node stepping at 10 Hz).
    assert r["node_step_rate_hz"] >= max(6.0, 0.8 * r["before_node_step_rate_hz"]), r
    assert r["color_rate_hz"] >= max(6.0, 0.8 * r["node_step_rate_hz"]), r
    assert r["color_lost"] is not None and r["color_lost"] <= 2, r
    assert rss1 - rss0 < 20 * 2**20


@pytest.mark.slow
@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT", "max-steps"])
def test_ros2_shutdown_leaves_complete_recordings_and_no_process(sample_scene, tmp_path, how):
    import psutil
    from rosbags.rosbag2 import Reader

    rec = tmp_path / "rec"
    extra = ["--max-steps", "15"] if how == "max-steps" else []
    p = _start_node(sample_scene, random.randint(101, 200), "--width", "160", "--height", "120",
                    "--record", str(rec), *extra)
    proc = psutil.Process(p.pid)
    end = time.monotonic() + 90
    while time.monotonic() < end and p.poll() is None and len(list(rec.glob("capture.partial/*"))) < 8:
        time.sleep(0.2)  # until the recorder has written a few frames
    time.sleep(1.0)
    children = proc.children(recursive=True) if p.poll() is None else []
    if how == "max-steps":
        rc, err = p.wait(timeout=60), p.stderr.read()
        assert rc == 0, err[-2000:]
    else:
        rc, err = _stop(p, getattr(signal, how))
        assert rc == 130, err[-2000:]
    assert "stopped after" in err
    assert not [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
    assert not list(rec.glob("*.partial")), list(rec.iterdir())
    with Reader(rec) as reader:  # metadata.yaml + the MCAP it names, complete
        n_clock = sum(c.msgcount for c in reader.connections if c.topic == "/clock")
        assert n_clock > 0 and reader.message_count == sum(1 for _ in reader.messages())
    if how == "max-steps":
        assert n_clock == 16  # the reset, then 15 steps
