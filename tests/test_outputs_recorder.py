"""Recorder sinks: MCAP read back with an independent library (rosbags: its own MCAP container
parser and CDR deserialiser with its built-in ROS 2 Humble types), capture folder round trip through
the KinectFusion importer, Ctrl-C leaves closed files, bounded queues drop oldest and count it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from presim.formats.depth_png import depth_to_png_u16
from presim.geometry import compose, make_pose, quat_xyzw_to_R
from presim.outputs.folder_recorder import FolderRecorder
from presim.outputs.mcap_recorder import McapConfig, McapRecorder
from presim.outputs.queue import BoundedWorker, QueuedSink
from presim.outputs.ros_msgs import MSGDEFS
from presim.outputs.sinks import build_sinks
from presim.testing.steps import synthetic_info, synthetic_steps

ROOT = Path(__file__).resolve().parents[1]


def _run_sinks(sinks, info, steps):
    for s in sinks:
        s.open(info)
    try:
        for r in steps:
            for s in sinks:
                s.on_step(r)
    finally:
        for s in sinks:
            s.close()


def read_mcap_rosbags(path: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log_time_ns, message)] read with rosbags (not the mcap library we write with)."""
    from rosbags.rosbag2.storage_mcap import McapReader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    reader = McapReader(Path(path))
    reader.open()
    try:
        out: dict[str, list] = {c.topic: [] for c in reader.connections}
        for conn, t_ns, raw in reader.messages(reader.connections):
            out[conn.topic].append((t_ns, ts.deserialize_cdr(bytes(raw), conn.msgtype)))
        types = {c.topic: c.msgtype for c in reader.connections}
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    finally:
        reader.close()
    return out, types, qos


def _T(tf) -> np.ndarray:
    t, q = tf.translation, tf.rotation
    return make_pose(quat_xyzw_to_R(np.array([q.x, q.y, q.z, q.w])), [t.x, t.y, t.z])


def _pose(p) -> np.ndarray:
    q = p.orientation
    return make_pose(quat_xyzw_to_R(np.array([q.x, q.y, q.z, q.w])), [p.position.x, p.position.y, p.position.z])


def test_msgdefs_match_rosbags_humble_types():
    """Our hand-written schemas parse (rosbags) to the same fields as rosbags' built-in Humble types."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in MSGDEFS.items():
        ours = get_types_from_msg(text, name)
        assert [f[0] for f in ours[name][1]] == [f[0] for f in ts.get_msgdef(name).fields], name


def test_mcap_reads_back_with_rosbags(tmp_path):
    n, every = 24, 2
    info = synthetic_info()
    steps = list(synthetic_steps(n, width=40, height=30, camera_every=every, drift_m=0.3))
    rec = McapRecorder(tmp_path / "rec.mcap", McapConfig(path_every_n_steps=5))
    _run_sinks([rec], info, steps)
    assert (tmp_path / "rec.mcap").is_file() and not (tmp_path / "rec.mcap.partial").exists()

    msgs, types, qos = read_mcap_rosbags(tmp_path / "rec.mcap")
    n_cam = len(range(0, n, every))
    expected = {"/tf": n, "/tf_static": 1, "/odom": n, "/joint_states": n, "/map_cloud": 1,
                "/head_camera/color/image_raw": n_cam, "/head_camera/color/camera_info": n_cam,
                "/head_camera/depth/image_raw": n_cam, "/head_camera/depth/camera_info": n_cam,
                "/path": 5,  # every 5 steps (4) + the rest at close (1)
                "/robot_description": 1, "/clock": n}
    assert {k: len(v) for k, v in msgs.items()} == expected
    assert types["/clock"] == "rosgraph_msgs/msg/Clock"
    clock_s = [m.clock.sec + m.clock.nanosec * 1e-9 for _, m in msgs["/clock"]]
    assert clock_s == pytest.approx([float(s.sim_time_s) for s in steps], abs=1e-9)  # one per step, sim time
    assert types["/tf"] == "tf2_msgs/msg/TFMessage" and types["/map_cloud"] == "sensor_msgs/msg/PointCloud2"
    assert msgs["/robot_description"][0][1].data == info.urdf_xml
    for latched in ("/tf_static", "/map_cloud", "/robot_description"):  # ros2 bag play re-sends them to late subscribers
        assert qos[latched][0].durability.name == "TRANSIENT_LOCAL"
    for topic, items in msgs.items():
        stamps = [t for t, _ in items]
        assert stamps == sorted(stamps), f"{topic}: log times not monotonic"

    # Images: sizes, encodings, exact pixels; depth REP-118 (NaN where invalid).
    cams = [r.cameras[0] for r in steps if r.cameras]
    for (t_ns, img), (_, dep), (_, ci), cam in zip(msgs["/head_camera/color/image_raw"],
                                                   msgs["/head_camera/depth/image_raw"],
                                                   msgs["/head_camera/color/camera_info"], cams):
        assert t_ns == round(cam.stamp_s * 1e9)
        assert (img.height, img.width, img.encoding, img.step) == (30, 40, "rgb8", 120)
        assert img.header.frame_id == "camera_optical_frame"
        np.testing.assert_array_equal(np.asarray(img.data).reshape(30, 40, 3), cam.color)
        assert (dep.encoding, dep.step) == ("32FC1", 160)
        d = np.frombuffer(np.asarray(dep.data).tobytes(), "<f4").reshape(30, 40)
        assert np.all(np.isnan(d[cam.depth_m == 0]))
        np.testing.assert_array_equal(d[cam.depth_m > 0], cam.depth_m[cam.depth_m > 0])
        np.testing.assert_allclose(np.asarray(ci.k).reshape(3, 3), cam.K.K)
        assert ci.header.stamp.sec + ci.header.stamp.nanosec * 1e-9 == pytest.approx(cam.stamp_s)

    # tf: map->odom->base_link == exact base pose; static + dynamic chain == exact camera pose.
    static = {tf.child_frame_id: (tf.header.frame_id, _T(tf.transform))
              for tf in msgs["/tf_static"][0][1].transforms}
    assert "camera_optical_frame" in static  # fixed joint
    cam_by_t = {round(r.sim_time_s * 1e9): r.cameras[0] for r in steps if r.cameras}
    for (t_ns, tfm), r in zip(msgs["/tf"], steps):
        edges = dict(static)
        edges.update({tf.child_frame_id: (tf.header.frame_id, _T(tf.transform)) for tf in tfm.transforms})
        assert all(tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec == t_ns for tf in tfm.transforms)

        def chain(frame):
            T = np.eye(4)
            while frame != "map":
                parent, T_pc = edges[frame]
                T, frame = compose(T_pc, T), parent
            return T

        np.testing.assert_allclose(chain("base_link"), r.T_world_base, atol=1e-9)
        np.testing.assert_allclose(edges["base_link"][1], r.odometry.T_odom_base, atol=1e-9)
        if t_ns in cam_by_t:
            np.testing.assert_allclose(chain("camera_optical_frame"), cam_by_t[t_ns].T_world_cam, atol=1e-9)

    # Odometry, joint states, path, cloud.
    for (_, od), r in zip(msgs["/odom"], steps):
        assert (od.header.frame_id, od.child_frame_id) == ("odom", "base_link")
        np.testing.assert_allclose(_pose(od.pose.pose), r.odometry.T_odom_base, atol=1e-9)
        assert od.twist.twist.angular.z == pytest.approx(r.odometry.twist_base[5])
    for (_, js), r in zip(msgs["/joint_states"], steps):
        assert list(js.name) == list(r.joint_states.names)
        np.testing.assert_allclose(js.position, r.joint_states.position)
    final_path = msgs["/path"][-1][1]
    assert len(final_path.poses) == n and final_path.header.frame_id == "map"
    np.testing.assert_allclose(_pose(final_path.poses[-1].pose), steps[-1].T_world_base, atol=1e-9)
    cloud = msgs["/map_cloud"][0][1]
    assert cloud.width == len(info.points_xyz) and cloud.point_step == 16
    buf = np.frombuffer(np.asarray(cloud.data).tobytes(), "<f4").reshape(-1, 4)
    np.testing.assert_array_equal(buf[:, :3], info.points_xyz)
    rgb = buf.view("<u4")[:, 3]
    np.testing.assert_array_equal((rgb >> 16) & 255, info.points_rgb[:, 0])


def test_mcap_is_partial_until_closed(tmp_path):
    rec = McapRecorder(tmp_path / "r.mcap")
    rec.open(synthetic_info())
    for r in synthetic_steps(3):
        rec.on_step(r)
    assert (tmp_path / "r.mcap.partial").exists() and not (tmp_path / "r.mcap").exists()
    rec.close()
    rec.close()  # idempotent
    assert (tmp_path / "r.mcap").exists() and not (tmp_path / "r.mcap.partial").exists()
    with pytest.raises(ValueError, match=r"\.mcap"):
        McapRecorder(tmp_path / "r.bag")


def test_capture_folder_round_trip_through_kinfu_importer(tmp_path):
    from presim.capture.importers import kinfu

    steps = list(synthetic_steps(6, width=40, height=30))
    rec = FolderRecorder(tmp_path / "capture")
    _run_sinks([rec], synthetic_info(), steps)
    assert kinfu.detect(tmp_path / "capture")
    scene = kinfu.read(tmp_path / "capture")
    assert len(scene) == 6
    for i, r in enumerate(steps):
        cam = r.cameras[0]
        np.testing.assert_allclose(scene.T_world_cam[i], cam.T_world_cam, atol=1e-8)
        assert scene.stamps_s[i] == pytest.approx(cam.stamp_s, abs=1e-9)
        fr = scene.frame(i)
        np.testing.assert_array_equal(fr.color, cam.color)
        np.testing.assert_allclose(fr.depth_m, depth_to_png_u16(cam.depth_m)[0] / 1000.0, atol=1e-6)
        assert np.all(fr.depth_m[cam.depth_m == 0] == 0)
        np.testing.assert_allclose(np.abs(fr.depth_m - cam.depth_m)[cam.depth_m > 0], 0, atol=5e-4)
    np.testing.assert_allclose(scene.intrinsics[0].K, steps[0].cameras[0].K.K)
    tum = np.loadtxt(tmp_path / "capture" / "trajectory_tum.txt")
    assert tum.shape == (6, 8)
    np.testing.assert_allclose(tum[:, 1:4], [r.cameras[0].T_world_cam[:3, 3] for r in steps], atol=1e-8)


def test_build_sinks_refuses_to_overwrite(tmp_path):
    (tmp_path / "capture").mkdir()
    with pytest.raises(FileExistsError, match="capture"):
        build_sinks(tmp_path, None, None)
    with pytest.raises(ValueError, match="viewer"):
        build_sinks(None, "vr", None)
    assert [type(s.inner).__name__ for s in build_sinks(tmp_path / "new", None, tmp_path / "a.rrd")] == \
        ["McapRecorder", "FolderRecorder", "RerunViewer"]


def test_an_rrd_file_viewer_queues_like_a_recorder(tmp_path):
    """A file-only rerun viewer is a recording: it gets the recorders' queue (a slow writer under
    load loses no step of a short drive), a live viewer the short one (it wants the newest)."""
    from presim.outputs.sinks import RECORDER_QUEUE, VIEWER_QUEUE

    sinks = build_sinks(tmp_path / "a", "rrd", None)
    assert [s.maxlen for s in sinks] == [RECORDER_QUEUE] * 3
    assert build_sinks(None, None, tmp_path / "b.rrd")[0].maxlen == RECORDER_QUEUE
    live = build_sinks(None, "web", None)
    assert live[0].maxlen == VIEWER_QUEUE < RECORDER_QUEUE


class _SlowSink:
    def __init__(self, delay_s):
        self.delay_s, self.seen = delay_s, []

    def open(self, info):
        pass

    def on_step(self, r):
        time.sleep(self.delay_s)
        self.seen.append(r.step_idx)

    def close(self):
        pass


def test_slow_sink_never_stalls_the_loop_and_drops_oldest():
    slow = _SlowSink(0.05)
    q = QueuedSink(slow, "slow", maxlen=4)
    q.open(synthetic_info())
    steps = list(synthetic_steps(60))
    t0 = time.perf_counter()
    for r in steps:
        q.on_step(r)
    loop_s = time.perf_counter() - t0
    q.close()
    assert loop_s < 0.5, f"loop waited for the sink: {loop_s:.2f} s for 60 steps"
    st = q.stats
    assert st.put == 60 and st.done + st.dropped == 60 and st.dropped >= 40 and st.max_depth == 4
    assert slow.seen[-1] == 59  # newest kept
    assert slow.seen == sorted(slow.seen)


def test_worker_error_is_reported_at_close():
    def boom(x):
        raise OSError("disk full")

    w = BoundedWorker("w", boom, maxlen=2)
    w.put(1)
    w.put(2)
    st = w.close()
    assert isinstance(w.error, OSError) and st.dropped == 2 and st.done == 0
    q = QueuedSink(type("S", (), {"open": lambda s, i: None, "on_step": lambda s, r: boom(r),
                                  "close": lambda s: None})(), "bad", 2)
    q.open(synthetic_info())
    q.on_step(next(synthetic_steps(1)))
    with pytest.raises(RuntimeError, match="disk full"):
        q.close()


_SIGINT_SCRIPT = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from presim.outputs.sinks import build_sinks
    from presim.sim.types import deliver
    from presim.testing.steps import synthetic_info, synthetic_steps
    out = Path(sys.argv[1])
    sinks = build_sinks(out, None, out / "view.rrd")
    for s in sinks:
        s.open(synthetic_info())
    try:
        for i, r in enumerate(synthetic_steps(100000, width=40, height=30)):
            deliver(sinks, r)  # as the simulator hands a step to its sinks
            if i == 5:
                (out / "started").write_text("x")
            time.sleep(0.01)
    finally:
        for s in sinks:
            s.close()
""")


def test_ctrl_c_while_a_step_is_handed_over_reaches_every_sink():
    """A SIGINT that arrives between two sinks' on_step: the step still reaches the later sinks,
    then KeyboardInterrupt is raised (without deliver the second sink would miss the step and the
    recordings would differ by one); the default handler is back afterwards."""
    from presim.sim.types import deliver

    got = []

    class _Sink:
        def __init__(self, name, interrupt=False):
            self.name, self.interrupt = name, interrupt

        def on_step(self, r):
            got.append((self.name, r))
            if self.interrupt:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # the signal is taken here, inside the first sink

    with pytest.raises(KeyboardInterrupt):
        deliver([_Sink("mcap", interrupt=True), _Sink("folder")], 7)
    assert got == [("mcap", 7), ("folder", 7)]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    terms = []  # a SIGTERM handler (presim commands raise the interrupt there) is held back too
    old = signal.signal(signal.SIGTERM, lambda signum, frame: terms.append(len(got)))
    try:
        class _Term(_Sink):
            def on_step(self, r):
                got.append((self.name, r))
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)

        deliver([_Term("mcap"), _Sink("folder")], 9)
    finally:
        signal.signal(signal.SIGTERM, old)
    assert got[-2:] == [("mcap", 9), ("folder", 9)] and terms == [len(got)]
    deliver([_Sink("mcap"), _Sink("folder")], 8)  # no signal: no exception
    assert got[-2:] == [("mcap", 8), ("folder", 8)]


def test_ctrl_c_leaves_closed_mcap_capture_and_rrd(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(_SIGINT_SCRIPT)
    out = tmp_path / "rec"
    env = dict(os.environ, PYTHONPATH=str(ROOT), PRESIM_NO_PROGRESS="1")
    p = subprocess.Popen([sys.executable, str(script), str(out)], env=env, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not (out / "started").exists():
            assert p.poll() is None, p.stderr.read().decode()
            assert time.monotonic() < deadline, "recorder subprocess did not start"
            time.sleep(0.1)
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        rc = p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    err = p.stderr.read().decode()
    assert rc != 0 and "KeyboardInterrupt" in err
    assert (out / "recording.mcap").is_file() and not (out / "recording.mcap.partial").exists()
    msgs, _, _ = read_mcap_rosbags(out / "recording.mcap")
    n = len(msgs["/tf"])
    assert n >= 6 and len(msgs["/head_camera/color/image_raw"]) == n
    assert (out / "capture" / "timestamps.txt").is_file()
    assert len((out / "capture" / "timestamps.txt").read_text().splitlines()) == n
    from rerun.chunk import RrdReader

    chunks = RrdReader(out / "view.rrd").stream().to_chunks()
    assert any(c.entity_path == "/world/scene" for c in chunks)
