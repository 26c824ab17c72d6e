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
