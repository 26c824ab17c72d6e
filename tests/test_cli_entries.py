"""The library entries the CLI calls (the CLI only parses and reports): open_scene, robot_for_scene,
run_drive and render_to_folder / output_intrinsics, on the small toy room."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from presim.capture.scene import SceneError
from presim.capture.open import open_scene
from presim.capture.store import save_scene
from presim.geometry import Intrinsics
from presim.sensors.camera import CameraSpec
from presim.sim.drive import ControllerSpec, DriveConfig, run_drive
from presim.sim.robot import robot_for_scene
from presim.sim.simulator import SimConfig
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory) -> Path:
    return save_scene(build_toy_room(ToyRoomConfig(width=64, height=48)), tmp_path_factory.mktemp("toy") / "toy")


def test_open_scene_one_error_type(toy_path, tmp_path):
    assert len(open_scene(toy_path)) == len(open_scene(str(toy_path)))
    with pytest.raises(SceneError, match="nope: scene folder not found"):
        open_scene(tmp_path / "nope")
    (tmp_path / "plain").mkdir()
    with pytest.raises(SceneError, match="plain: not a saved scene"):
        open_scene(tmp_path / "plain")
    (tmp_path / "half.partial").mkdir()
    with pytest.raises(SceneError, match="interrupted save"):
        open_scene(tmp_path / "half")
    with pytest.raises(SceneError, match="no importer recognises"):  # allowed, but nothing reads an empty folder
        open_scene(tmp_path / "plain", allow_capture=True)


def test_open_scene_imports_a_capture_when_allowed(tmp_path):
    from presim.formats.kinfu_folder import KinfuFolderWriter

    K = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
    w = KinfuFolderWriter(tmp_path / "cap")
    (tmp_path / "cap").mkdir()
    for i in range(2):
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        w.write_frame(np.full((24, 32, 3), 100, np.uint8), np.full((24, 32), 1.5, np.float32), T, K, 0.1 * i)
    w.close()
    notes = []
    scene = open_scene(tmp_path / "cap", allow_capture=True, on_import=notes.append)
    assert len(scene) == 2 and scene.meta.source_format == "kinfu"
    assert len(notes) == 1 and "importing it on the fly" in notes[0]


def test_robot_for_scene():
    assert robot_for_scene(None, has_floor=False).drive == "free"
    r = robot_for_scene(None, has_floor=True, drive="holonomic", head_tilt_rad=0.25)
    assert r.urdf_path.name == "presim_bot.urdf" and r.drive == "holonomic"
    assert dict(r.config.initial_joint_positions) == {"head_tilt_joint": 0.25}
    assert robot_for_scene("default", has_floor=False).config.initial_joint_positions == ()
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        robot_for_scene("nope.urdf", has_floor=True)


class _CountingSink:
    def __init__(self):
        self.calls = []

    def open(self, info):
        self.calls.append("open")

    def on_step(self, result):
        self.calls.append("step")

    def close(self):
        self.calls.append("close")


def test_run_drive_route_stats_and_sinks(toy_path):
    scene = open_scene(toy_path)
    sink = _CountingSink()
    made = []
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=16, height=12, rate_hz=10.0),))
    st = run_drive(scene, robot_for_scene(None, True), cfg, ControllerSpec(), DriveConfig(steps=7, seed=1),
                   make_sinks=lambda: made.append(1) or [sink])
    # The sinks see the reset's result too: 1 + 7 steps, then close.
    assert made == [1] and sink.calls == ["open"] + ["step"] * 8 + ["close"]
    assert st.steps == 7 and st.images == 7 and st.sim_time_s == pytest.approx(0.7)
    assert st.distance_m >= 0 and st.T_world_base.shape == (4, 4) and "total" in st.stage_ms_per_step


def test_run_drive_bad_controller_makes_no_sinks(toy_path, tmp_path):
    scene = open_scene(toy_path)
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=16, height=12),))
    made = []
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3\n")
    with pytest.raises(ValueError, match="bad.txt:1"):
        run_drive(scene, robot_for_scene(None, True), cfg, ControllerSpec("trajectory", bad),
                  make_sinks=lambda: made.append(1) or [])
    with pytest.raises(ValueError, match="free camera rig takes --trajectory"):
        run_drive(scene, robot_for_scene("free", True), cfg, ControllerSpec("waypoints", bad),
                  make_sinks=lambda: made.append(1) or [])
    assert made == []


def test_output_intrinsics():
    from presim.cli.render_job import output_intrinsics

    K = Intrinsics(500.0, 510.0, 319.5, 239.5, 640, 480)
    assert output_intrinsics(K) == K
    half = output_intrinsics(K, width=320)
    assert half.size_wh == (320, 240) and half.fx == pytest.approx(250.0) and half.cx == pytest.approx(159.5)
    assert output_intrinsics(K, fx=100.0, cy=10.0) == Intrinsics(100.0, 510.0, 319.5, 10.0, 640, 480)


def test_render_to_folder_is_a_capture_folder(toy_path, tmp_path):
    from presim.capture.importers import kinfu
    from presim.cli.render_job import render_to_folder
    from presim.synthesis.renderer import RenderConfig

    scene = open_scene(toy_path)
    T = scene.T_world_cam[[0, 3]]
    s = render_to_folder(scene, T, np.array([0.0, 0.5]), scene.intrinsics[0], tmp_path / "r", RenderConfig())
    assert s["num_frames"] == 2 and s["depth_clipped_px"] == 0
    back = kinfu.read(tmp_path / "r")
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-9)
    np.testing.assert_allclose(back.stamps_s, [0.0, 0.5])
    assert (tmp_path / "r" / "frame-000001.valid.png").is_file() and (tmp_path / "r" / "render.json").is_file()
