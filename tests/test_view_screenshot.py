"""``presim view FILE.rrd --screenshot out.png``: a still image of a recording for a server user (scene
points, input views, trajectories, the robot's last pose, the last colour and depth images)."""

from __future__ import annotations

import numpy as np
import pytest

from presim.cli import main
from presim.io_utils import read_image
from presim.outputs.queue import QueuedSink
from presim.outputs.rrd_snapshot import read_rrd
from presim.outputs.viewer import RerunViewer, ViewerConfig
from presim.testing.steps import synthetic_info, synthetic_steps


@pytest.fixture(scope="module")
def rrd(tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "drive.rrd"
    steps = list(synthetic_steps(10, width=32, height=24, camera_every=3))
    v = QueuedSink(RerunViewer("rrd", path, ViewerConfig(trajectory_every_n_steps=4)), "v", 64)
    v.open(synthetic_info(num_views=5))
    for r in steps:
        v.on_step(r)
    v.close()
    return path, steps


def test_read_rrd_gets_what_was_logged(rrd):
    path, steps = rrd
    rec = read_rrd(path)
    assert rec.steps == steps[-1].step_idx
    assert len(rec.input_T_world_cam) == 5 and len(rec.points_xyz) > 0 and rec.points_rgb.shape == rec.points_xyz.shape
    np.testing.assert_allclose(rec.T_world_base, steps[-1].T_world_base, atol=1e-5)
    np.testing.assert_allclose(rec.base_path[-1, :2], steps[-1].T_world_base[:2, 3], atol=1e-5)
    last_cam = [r for r in steps if r.cameras][-1].cameras[0]
    np.testing.assert_array_equal(rec.color, last_cam.color)
    np.testing.assert_allclose(rec.depth_m, last_cam.depth_m)


def test_view_screenshot_writes_png(rrd, tmp_path, capsys):
    path, _ = rrd
    out = tmp_path / "shot.png"
    assert main(["view", str(path), "--screenshot", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    img = read_image(out, kind="color")
    assert img.shape[:2] == (900, 1600)
    right = img[:, 1000:]  # the camera image panels are not blank
    assert right.std() > 5


def test_view_screenshot_refuses_a_bad_file(tmp_path, capsys):
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not a recording")
    assert main(["view", str(bad), "--screenshot", str(tmp_path / "x.png")]) == 1
    assert "bad.rrd" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
