"""Sinks on the real simulator: a drive in the toy room recorded to MCAP (read back with rosbags,
tf against the simulator's exact poses), the capture folder re-imported, and the `presim drive
--record --rrd` command interrupted with Ctrl-C leaving closed, readable files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from presim.geometry import compose

from test_outputs_recorder import _T, read_mcap_rosbags

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def toy_scene(tmp_path_factory):
    from presim.capture.store import save_scene
    from presim.testing.toy_scene import build_toy_room

    dst = tmp_path_factory.mktemp("e2e") / "toyroom"
    save_scene(build_toy_room(), dst)
    return dst


def test_simulator_drive_recorded_and_read_back(toy_scene, tmp_path):
    from presim.capture.importers import kinfu
    from presim.capture.importers.registry import detect_format
    from presim.capture.store import load_scene
    from presim.outputs.sinks import build_sinks
    from presim.sensors.camera import CameraSpec
    from presim.sensors.odometry import OdometryConfig
    from presim.sim.simulator import SimConfig, Simulator
    from rerun.chunk import RrdReader

    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=96, height=72, rate_hz=5.0),),
                    odometry=OdometryConfig(drift=True))
    sim = Simulator(load_scene(toy_scene), config=cfg)
    for s in build_sinks(tmp_path / "rec", "rrd", None):
        sim.add_sink(s)
    results = []
    with sim:
        results.append(sim.reset(seed=3, start=np.array([2.5, 2.0, np.pi])))
        for i in range(20):
            results.append(sim.step(np.array([0.3, 0.0, 0.2 if i > 10 else 0.0])))
    msgs, _, _ = read_mcap_rosbags(tmp_path / "rec" / "recording.mcap")
    assert len(msgs["/tf"]) == len(results) == 21
    n_img = sum(len(r.cameras) for r in results)
    assert 9 <= n_img <= 12 and len(msgs["/head_camera/color/image_raw"]) == n_img
    static = {tf.child_frame_id: (tf.header.frame_id, _T(tf.transform)) for tf in msgs["/tf_static"][0][1].transforms}
    cams = {round(c.stamp_s * 1e9): c for r in results for c in r.cameras}
    for (t_ns, tfm), r in zip(msgs["/tf"], results):
        assert t_ns == round(r.sim_time_s * 1e9)
        edges = dict(static)
        edges.update({tf.child_frame_id: (tf.header.frame_id, _T(tf.transform)) for tf in tfm.transforms})

        def chain(frame):
            T = np.eye(4)
            while frame != "map":
                parent, T_pc = edges[frame]
                T, frame = compose(T_pc, T), parent
            return T

        np.testing.assert_allclose(chain("base_link"), r.T_world_base, atol=1e-9)
        if t_ns in cams:
            np.testing.assert_allclose(chain("camera_optical_frame"), cams[t_ns].T_world_cam, atol=1e-9)
    for (_, img), c in zip(msgs["/head_camera/color/image_raw"], [c for r in results for c in r.cameras]):
        np.testing.assert_array_equal(np.asarray(img.data).reshape(72, 96, 3), c.color)
    # odometry drift is on: map->odom is not the identity by the end, but map->base stays exact
    last_odom = [tf for tf in msgs["/tf"][-1][1].transforms if tf.child_frame_id == "odom"][0]
    assert np.abs(_T(last_odom.transform) - np.eye(4)).max() > 1e-6

    cap = tmp_path / "rec" / "capture"
    assert detect_format(cap) == "kinfu"
    scene = kinfu.read(cap)
    assert len(scene) == n_img
    np.testing.assert_allclose(scene.T_world_cam, [c.T_world_cam for r in results for c in r.cameras], atol=1e-8)
    chunks = RrdReader(tmp_path / "rec" / "recording.rrd").stream().to_chunks()
    assert sum(c.num_rows for c in chunks if c.entity_path == "/world/robot/base_link") == 21


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_presim_drive_ctrl_c_leaves_valid_recordings(toy_scene, tmp_path, sig):
    from rerun.chunk import RrdReader

    out = tmp_path / "rec"
    env = dict(os.environ, PYTHONPATH=str(ROOT), PRESIM_NO_PROGRESS="1")
    # a route of minutes (the built-in one ends after ~17 s, which a loaded machine's recorder can
    # outlast before frame 5 is on disk: the signal then came after a normal exit)
    wp = tmp_path / "back_and_forth.txt"
    wp.write_text("2.0 1.0\n2.0 3.0\n" * 50)
    cmd = [sys.executable, "-m", "presim", "drive", str(toy_scene), "--waypoints", str(wp), "--steps", "100000",
           "--realtime",
           "--width", "64", "--height", "48", "--record", str(out), "--rrd", str(out / "drive.rrd")]
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while not (out / "capture.partial" / "frame-000005.pose.txt").exists():
            assert p.poll() is None, p.stdout.read().decode()
            assert time.monotonic() < deadline, "drive did not start recording"
            time.sleep(0.2)
        p.send_signal(sig)
        p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    log = p.stdout.read().decode()
    assert (out / "recording.mcap").is_file() and not (out / "recording.mcap.partial").exists(), log
    msgs, _, _ = read_mcap_rosbags(out / "recording.mcap")
    assert len(msgs["/tf"]) >= 6
    assert (out / "capture" / "trajectory_tum.txt").is_file()
    assert not (out / "drive.rrd.partial").exists() and p.returncode == 130, log
    chunks = RrdReader(out / "drive.rrd").stream().to_chunks()
    assert any(c.entity_path == "/world/scene" for c in chunks)
