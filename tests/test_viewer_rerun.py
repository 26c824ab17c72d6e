"""rerun viewer sink: the .rrd reads back with rerun's own API (entity paths follow the frame tree,
counts, sim-time timeline); the served web viewer binds 127.0.0.1 only and renders the scene in
headless Chromium."""

from __future__ import annotations

import colorsys
import dataclasses
import os

import numpy as np
import pytest

from presim.outputs.queue import QueuedSink
from presim.testing.steps import synthetic_info, synthetic_steps
from presim.outputs.viewer import RerunViewer, ViewerConfig

CAM = "/world/robot/base_link/head_pan_link/head_tilt_link/camera_link/camera_optical_frame"


def _rows(chunks) -> dict[str, int]:
    out: dict[str, int] = {}
    for c in chunks:
        out[c.entity_path] = out.get(c.entity_path, 0) + c.num_rows
    return out


def _column(chunks, entity: str, name: str) -> list:
    vals = []
    for c in chunks:
        if c.entity_path == entity and not c.is_static:
            rb = c.to_record_batch()
            if name in rb.schema.names:
                vals += rb.column(name).to_pylist()
    return vals


def test_rrd_reads_back_with_rerun(tmp_path):
    from rerun.chunk import RrdReader

    n = 12
    info = synthetic_info(num_views=5)
    steps = list(synthetic_steps(n, width=32, height=24, camera_every=3))
    v = QueuedSink(RerunViewer("rrd", tmp_path / "drive.rrd", ViewerConfig(trajectory_every_n_steps=4)), "v", 64)
    v.open(info)
    for r in steps:
        v.on_step(r)
    v.close()
    assert v.stats.dropped == 0

    reader = RrdReader(tmp_path / "drive.rrd")
    assert [e.application_id for e in reader.recordings()] == ["presim"]
    chunks = reader.stream().to_chunks()
    rows = _rows(chunks)
    for i in range(5):
        assert f"/world/inputs/view_{i:04d}" in rows
    assert "/world/inputs/view_0005" not in rows
    assert rows["/world/scene"] == 1
    assert rows["/world/robot/base_link"] == n
    n_cam = len(range(0, n, 3))
    assert rows[f"{CAM}/color"] == n_cam and rows[f"{CAM}/depth"] == n_cam
    # the moving joint's link is logged every step, fixed links once (static)
    assert rows["/world/robot/base_link/head_pan_link"] == n
    assert rows["/world/robot/base_link/head_pan_link/head_tilt_link/camera_link"] == 1
    assert rows["/world/trajectory/base"] >= n // 4
    sim_t = _column(chunks, "/world/robot/base_link", "sim_time")
    assert len(sim_t) == n
    secs = sorted(t.total_seconds() if hasattr(t, "total_seconds") else t / 1e9 for t in sim_t)
    np.testing.assert_allclose(secs, [r.sim_time_s for r in steps], atol=1e-6)
    meters = _column(chunks, f"{CAM}/depth", "DepthImage:meter")
    assert meters and all(np.allclose(np.asarray(m, dtype=float), 1.0) for m in meters)
    trans = _column(chunks, "/world/robot/base_link", "Transform3D:translation")
    got = np.array([np.asarray(t, dtype=float).ravel()[:3] for t in trans])
    want = np.array([r.T_world_base[:3, 3] for r in steps])
    np.testing.assert_allclose(got[np.lexsort(got.T[::-1])], want[np.lexsort(want.T[::-1])], atol=1e-5)


def test_viewer_rejects_bad_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"):
        RerunViewer("vr")
    with pytest.raises(ValueError, match="rrd"):
        RerunViewer("rrd")
    with pytest.raises(ValueError, match=r"\.rrd"):
        RerunViewer("rrd", tmp_path / "x.mcap")


def _colorful_info():
    info = synthetic_info(num_points=40000)
    rng = np.random.default_rng(1)
    xyz = rng.uniform([-1.5, -1.5, 0.0], [1.5, 1.5, 2.0], size=(40000, 3)).astype(np.float32)
    hue = (xyz[:, 0] + 1.5) / 3.0
    rgb = np.array([colorsys.hsv_to_rgb(h, 1.0, 1.0) for h in hue]) * 255
    return dataclasses.replace(info, points_xyz=xyz, points_rgb=rgb.astype(np.uint8))


def _listening_ips(pid: int) -> set[str]:
    import psutil

    ips = set()
    procs = [psutil.Process(pid)] + psutil.Process(pid).children(recursive=True)
    for p in procs:
        for c in p.net_connections(kind="inet"):
            if c.status == psutil.CONN_LISTEN:
                ips.add(c.laddr.ip)
    return ips


@pytest.mark.browser
def test_web_viewer_binds_loopback_and_renders_scene(tmp_path):
    from presim.testing.browser import find_browser, saturated_fraction, save_png, screenshot

    try:
        find_browser()
    except FileNotFoundError as e:
        if os.environ.get("CI") == "true":
            raise
        pytest.skip(str(e))
    viewer = RerunViewer("web", tmp_path / "web.rrd")
    viewer.open(_colorful_info())
    try:
        assert _listening_ips(viewer.process.pid) == {"127.0.0.1"}
        assert viewer.url.startswith("http://127.0.0.1:")
        for r in synthetic_steps(5, width=32, height=24):
            # No camera images: the colored pixels must come from the 3D scene view.
            viewer.on_step(dataclasses.replace(r, cameras=()))
        viewer.flush()
        img = screenshot(viewer.url, lambda im: saturated_fraction(im) > 0.03, timeout_s=90)
        save_png(tmp_path / "web_viewer.png", img)
        frac = saturated_fraction(img)
        assert img.std() > 10, "blank screenshot"
        assert frac > 0.03, f"scene cloud not visible: {frac:.3%} colored pixels (see {tmp_path}/web_viewer.png)"
    finally:
        viewer.close()
    assert viewer.process is None
    from rerun.chunk import RrdReader

    assert "/world/scene" in _rows(RrdReader(tmp_path / "web.rrd").stream().to_chunks())


def test_native_mode_streams_on_loopback_and_saves_rrd(tmp_path):
    """Native viewer started headless (no display here): bound to 127.0.0.1, data also in the .rrd."""
    import psutil
    from rerun.chunk import RrdReader

    v = RerunViewer("native", tmp_path / "n.rrd", ViewerConfig(extra_viewer_args=("--headless",)))
    v.open(synthetic_info())
    pid = v.process.pid
    try:
        assert _listening_ips(pid) == {"127.0.0.1"}
        for r in synthetic_steps(3, width=16, height=12):
            v.on_step(r)
        v.close()
        assert "/world/robot/base_link" in _rows(RrdReader(tmp_path / "n.rrd").stream().to_chunks())
    finally:
        p = psutil.Process(pid)  # native viewers outlive the run on purpose; this one is ours to stop
        p.terminate()
        p.wait(10)


def test_robot_visuals_from_urdf():
    from presim.outputs.viewer import robot_visuals
    from presim.sim.robot import default_robot

    vis = robot_visuals(default_robot().urdf_xml)
    assert [(v.link, v.kind) for v in vis] == [("base_link", "cylinder"), ("base_link", "cylinder"),
                                               ("head_pan_link", "cylinder"), ("head_tilt_link", "box")]
    assert vis[0].size == (0.25, 0.30)
    np.testing.assert_allclose(vis[3].size, (0.12, 0.20, 0.10))


def test_blueprint_eye_behind_above_robot_and_separate_image_panels():
    import rerun.blueprint as rrb

    from presim.geometry import make_pose, rotation_z
    from presim.outputs.viewer import viewer_blueprint

    T = make_pose(rotation_z(np.pi / 2), [1.0, 2.0, 0.0])   # robot at (1, 2) facing +y
    bp = viewer_blueprint("world/robot/base_link", T, "world/robot/cam")
    view3d, images = bp.root_container.contents
    assert isinstance(view3d, rrb.Spatial3DView) and view3d.origin == "world"
    eye = view3d.properties["EyeControls3D"]
    text = repr(eye)
    assert "world/robot/base_link" in text                       # the eye follows the robot
    pos = np.array([float(x) for x in text.split("position=[[")[1].split("]]")[0].split(",")])
    np.testing.assert_allclose(pos, [1.0, -0.5, 2.5], atol=1e-9)   # 2.5 m behind (-y), 2.5 m up
    color, depth = images.contents
    assert isinstance(color, rrb.Spatial2DView) and isinstance(depth, rrb.Spatial2DView)
    assert (color.origin, color.contents) == ("world/robot/cam", "world/robot/cam/color")
    assert (depth.origin, depth.contents) == ("world/robot/cam", "world/robot/cam/depth")


def test_rrd_has_robot_links_blueprint_and_no_ceiling(tmp_path):
    import subprocess

    from rerun.chunk import RrdReader

    from presim.outputs.viewer import rerun_executable

    info = dataclasses.replace(synthetic_info(num_points=3000), floor_z_m=0.0)   # points up to 2.5 m
    v = RerunViewer("rrd", tmp_path / "bp.rrd")
    v.open(info)
    for r in synthetic_steps(3, width=32, height=24):
        v.on_step(r)
    v.close()
    chunks = RrdReader(tmp_path / "bp.rrd").stream().to_chunks()
    rows = _rows(chunks)
    assert "/world/robot/base_link/visual_0" in rows and "/world/robot/base_link/body" not in rows
    assert "/world/robot/base_link/head_pan_link/head_tilt_link/visual_3" in rows
    scene = [c.to_record_batch() for c in chunks if c.entity_path == "/world/scene"]
    pos = np.array(scene[0].column("Points3D:positions").to_pylist()[0])
    assert len(pos) < 3000 and pos[:, 2].max() <= 2.0 + 1e-6 and pos[:, 2].max() > 1.8  # clipped at 2 m
    out = subprocess.run(rerun_executable() + ["rrd", "print", str(tmp_path / "bp.rrd")], capture_output=True,
                         text=True, env=dict(os.environ, RERUN_ANALYTICS="0"), timeout=60).stdout
    assert "EyeControls3D:tracking_entity" in out
    assert out.count("ViewBlueprint:class_identifier") == 3      # one 3D view, colour and depth panels


def test_live_viewer_drops_images_to_wall_rate():
    v = RerunViewer("web", config=ViewerConfig(live_max_image_hz=5.0))
    assert v._image_due("cam") and not v._image_due("cam") and v._image_due("other")
    assert all(RerunViewer("rrd", "x.rrd")._image_due("cam") for _ in range(3))   # files keep every image


def test_web_viewer_keep_open_serves_after_close(tmp_path):
    import signal

    import psutil

    from presim.outputs.viewer import wait_for_port

    v = RerunViewer("web", config=ViewerConfig(keep_open=True))
    v.open(synthetic_info(num_points=100))
    proc = v.process
    try:
        for r in synthetic_steps(2, width=16, height=12):
            v.on_step(r)
        v.close()
        assert v.kept_open and proc.poll() is None
        port = int(v.url.split("://127.0.0.1:")[1].split("/")[0])
        wait_for_port("127.0.0.1", port, 5)                       # still serving the page
        os.killpg(proc.pid, signal.SIGTERM)                        # what Ctrl-C ends
        v.wait_closed()
        assert v.process is None and not psutil.pid_exists(proc.pid) or proc.poll() is not None
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_drive_keep_open_needs_web_viewer(tmp_path, capsys):
    from presim.cli import main

    assert main(["drive", str(tmp_path / "missing"), "--keep-open"]) == 1
    assert "--keep-open" in capsys.readouterr().err
