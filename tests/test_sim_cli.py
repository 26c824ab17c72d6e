"""``presim drive``: built-in routes (mobile base in the sample scene, free camera on a real tabletop
capture), waypoints, TUM replay of a recording, recording through the sinks, clear errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from presim.capture.store import save_scene
from presim.cli import main
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory) -> Path:
    return save_scene(build_toy_room(ToyRoomConfig(width=160, height=120)), tmp_path_factory.mktemp("toy") / "toy")


def _summary(out: str) -> dict:
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("steps "))
    tok = line.split()
    return {"steps": int(tok[1]), "distance": float(tok[tok.index("distance") + 1]),
            "contacts": int(tok[tok.index("contacts") + 1]), "images": int(tok[-1])}


def test_drive_builtin_route_toy(toy_path, capsys):
    assert main(["drive", str(toy_path), "--steps", "60", "--width", "32", "--height", "24", "--seed", "1"]) == 0
    s = _summary(capsys.readouterr().out)
    assert s["steps"] == 60 and s["images"] == 60 and s["distance"] > 0.3


@pytest.mark.parametrize("how", [["--waypoints"], ["--controller", "waypoints"]], ids=["flag", "controller"])
def test_drive_waypoints(toy_path, tmp_path, capsys, how):
    wp = tmp_path / "wp.txt"
    wp.write_text("2.0 1.0\n2.0 3.0\n")
    assert main(["drive", str(toy_path), *how, str(wp), "--steps", "300", "--width", "16",
                 "--height", "12", "--rate-hz", "1"]) == 0
    out = capsys.readouterr().out
    s = _summary(out)
    assert s["steps"] < 300  # stopped because the follower finished
    final = out.split("final base pose x ")[1].split()
    assert np.hypot(float(final[0]) - 2.0, float(final[2]) - 3.0) < 0.2


def test_drive_errors(toy_path, tmp_path, capsys):
    assert main(["drive", str(tmp_path / "nope")]) == 1
    assert "nope: scene folder not found" in capsys.readouterr().err
    assert main(["drive", str(toy_path), "--robot", str(tmp_path / "r.urdf")]) == 1
    assert "r.urdf: URDF file not found" in capsys.readouterr().err
    assert main(["drive", str(toy_path), "--camera-link", "eye", "--steps", "1"]) == 1
    assert "camera link 'eye'" in capsys.readouterr().err
    bad = tmp_path / "t.txt"
    bad.write_text("1 2 3\n")
    assert main(["drive", str(toy_path), "--trajectory", str(bad)]) == 1
    assert "t.txt:1" in capsys.readouterr().err
    assert main(["drive", str(toy_path), "--controller", "trajectory", str(bad)]) == 1
    assert "t.txt:1" in capsys.readouterr().err
    assert main(["drive", str(toy_path), "--controller", "waypoints"]) == 1
    assert "expected 'keyboard', 'route', 'waypoints FILE'" in capsys.readouterr().err


@pytest.mark.slow
def test_scripted_drive_sample_scene_record_and_replay(tmp_path, capsys):
    """Built-in route through the sample scene, recorded; replaying the recorded trajectory
    reproduces the camera poses."""
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    scene = build_sample_scene(tmp_path / "scene", seed=0, config=SampleSceneConfig(width=160, height=120, num_frames=30))
    rec = tmp_path / "rec"
    assert main(["drive", str(scene), "--steps", "30", "--width", "80", "--height", "60", "--record", str(rec)]) == 0
    s = _summary(capsys.readouterr().out)
    assert s["steps"] == 30 and s["images"] == 31 - 1 and s["distance"] > 0.3
    cap = rec / "capture"
    assert len(list(cap.glob("frame-*.color.png"))) == 31  # reset + 30 steps
    traj = np.loadtxt(cap / "trajectory_tum.txt")
    # The base stays on the floor: the camera height only changes with the head tilt (1.05 m pivot).
    assert np.all((traj[:, 3] > 1.0) & (traj[:, 3] < 1.11))
    rec2 = tmp_path / "rec2"
    assert main(["drive", str(scene), "--trajectory", str(cap / "trajectory_tum.txt"), "--steps", "30",
                 "--width", "80", "--height", "60", "--record", str(rec2)]) == 0
    traj2 = np.loadtxt(rec2 / "capture" / "trajectory_tum.txt")
    assert traj2.shape == traj.shape and np.allclose(traj2, traj, atol=1e-6)


def test_scripted_drive_free_camera_on_tabletop_capture(shared_data, tmp_path, capsys):
    apc = shared_data("apc_cardboard_bin_kinfu50")
    from presim.capture.importers.registry import import_capture

    scene = save_scene(import_capture(apc, every=2), tmp_path / "apc")
    rec = tmp_path / "rec"
    assert main(["drive", str(scene), "--steps", "12", "--width", "64", "--height", "48", "--seed", "3",
                 "--record", str(rec)]) == 0
    out = capsys.readouterr().out
    assert "presim_free_camera" in out or "free_camera.urdf" in out
    s = _summary(out)
    assert s["steps"] == 12 and s["contacts"] == 0 and s["images"] == 12
    traj = np.loadtxt(rec / "capture" / "trajectory_tum.txt")
    # The path stays near the captured views (a few cm of sway around them).
    from presim.capture.store import load_scene

    centres = load_scene(scene).camera_centres
    d = np.linalg.norm(traj[:, None, 1:4] - centres[None], axis=2).min(axis=1)
    assert d.max() < 0.1


def test_drive_render_budget_defaults(toy_path, monkeypatch, capsys):
    """--render-budget-ms: 0 (reproducible images) unless paced to wall time (80 ms); explicit wins;
    the simulator's point cache is bounded (SIM_RENDER_CACHE_MB)."""
    import presim.sim.drive as drive
    from presim.cli.sim_cmds import REALTIME_RENDER_BUDGET_MS
    from presim.sim.simulator import SIM_RENDER_CACHE_MB

    seen = []

    def fake_run_drive(scene, robot, sim_config, *a, **k):
        seen.append(sim_config)
        raise ValueError("stop here")

    monkeypatch.setattr(drive, "run_drive", fake_run_drive)
    base = ["drive", str(toy_path), "--steps", "1", "--width", "16", "--height", "12"]
    for extra, budget in (([], 0.0), (["--realtime"], REALTIME_RENDER_BUDGET_MS),
                          (["--realtime", "--render-budget-ms", "0"], 0.0), (["--render-budget-ms", "25"], 25.0)):
        assert main(base + extra) == 1 and "stop here" in capsys.readouterr().err
        assert seen[-1].render.time_budget_ms == budget and seen[-1].perf.cache_mb == SIM_RENDER_CACHE_MB
    assert main(base + ["--render-budget-ms", "-1"]) == 1
    assert "--render-budget-ms must be >= 0" in capsys.readouterr().err
