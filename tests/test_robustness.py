"""Issue 16: every row of its table gives a one-line error, a warning, or survives (the ROS rows
are in test_ros_bridge.py, the MCAP /clock in test_outputs_recorder.py). CLI calls run in-process
through ``presim.cli.main`` on the toy room (160x120, 12 frames)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from presim.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    monkeypatch.delenv("PRESIM_MAX_MEMORY", raising=False)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    from presim.capture.store import save_scene
    from presim.testing.toy_scene import build_toy_room

    dst = tmp_path_factory.mktemp("robust") / "toyroom"
    save_scene(build_toy_room(), dst)
    return dst


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def one_line_error(err: str, *words: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


# ---- limits (pure) ------------------------------------------------------------------------------
def test_parse_size_and_budget(monkeypatch):
    from presim.limits import InputError, memory_budget_bytes, parse_size

    assert parse_size("64G") == 64 * 2**30 and parse_size("512M") == 512 * 2**20 and parse_size("1000") == 1000
    assert parse_size("1.5GiB") == int(1.5 * 2**30)
    for bad in ("", "x", "-1G", "0", "nanG", "5Q"):
        with pytest.raises(InputError, match="--max-memory"):
            parse_size(bad)
    monkeypatch.setenv("PRESIM_MAX_MEMORY", "3G")
    assert memory_budget_bytes() == 3 * 2**30 and memory_budget_bytes("1G") == 2**30


def test_render_estimate_known_numbers():
    from presim.limits import check_render_memory, render_memory_bytes, MemoryLimitError

    # (2 * 7 bytes per layer + 96) per pixel: 640x480 with 4 layers = 307200 * 152 bytes
    assert render_memory_bytes(640, 480, 4) == 307200 * 152
    assert render_memory_bytes(100, 100, 1) == 10000 * 110
    with pytest.raises(MemoryLimitError, match=r"^--layers \(100x100, 1000 layers\)"):
        check_render_memory(100, 100, 1000, max_memory="10M")  # 4 layers would fit: the layers are to blame
    with pytest.raises(MemoryLimitError, match=r"^--width/--height"):
        check_render_memory(10000, 10000, 4, max_memory="10M")
    assert check_render_memory(100, 100, 4, max_memory="10M") == 10 * 2**20


# ---- render -------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, words", [
    (["--width", "0"], ["--width", "at least 1", "0"]),
    (["--width", "-5"], ["--width", "-5"]),
    (["--height", "0"], ["--height"]),
    (["--fx", "0"], ["--fx", "positive"]),
    (["--fy", "nan"], ["--fy", "nan"]),
    (["--cx", "inf"], ["--cx", "finite"]),
    (["--layers", "0"], ["--layers"]),
    (["--width", "100000"], ["--width/--height (100000x75000", "estimated", "limit"]),
    (["--layers", "100000"], ["--layers (160x120, 100000 layers)", "estimated", "limit"]),
    (["--max-memory", "junk"], ["--max-memory", "junk"]),
])
def test_render_refuses_bad_sizes_in_one_line(capsys, tmp_path, toy, args, words):
    rc, _, err = run_cli(capsys, "render", toy, "--frame", "0", "--out", tmp_path / "r", *args)
    assert rc == 1
    one_line_error(err, "presim render: error:", *words)
    assert not (tmp_path / "r").exists()  # refused before anything was written


def test_max_memory_raises_the_limit(capsys, tmp_path, toy):
    # 160x120 with 2000 layers: 19200 * (14 * 2000 + 96) B = 539443200 B = 514.45 MiB estimated
    rc, _, err = run_cli(capsys, "render", toy, "--frame", "0", "--out", tmp_path / "r", "--layers", "2000",
                         "--max-memory", "100M")
    assert rc == 1 and "514.5 MiB" in err and "100.0 MiB (--max-memory" in err
    rc, _, err = run_cli(capsys, "render", toy, "--frame", "0", "--out", tmp_path / "r", "--width", "32",
                         "--layers", "2000", "--max-memory", "2G")
    assert rc == 0, err


def test_render_warns_when_the_pose_is_far_from_the_capture(capsys, tmp_path, toy):
    rc, _, err = run_cli(capsys, "render", toy, "--pose", "100 0 1 0 0 0 1", "--out", tmp_path / "far",
                         "--width", "32")
    assert rc == 0
    line = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(line) == 1 and " m from the nearest captured view" in line[0] and "100% of the image" in line[0]
    rc, _, err = run_cli(capsys, "render", toy, "--frame", "3", "--out", tmp_path / "near", "--width", "32")
    assert rc == 0 and "warning" not in err  # at a captured pose: no warning


def test_far_poses_known_distance(toy):
    from presim.capture.store import load_scene
    from presim.cli.render_job import far_poses

    scene = load_scene(toy)
    T = scene.T_world_cam[[0, 0]].copy()
    T[1, :3, 3] += [0.0, 0.0, 5.0]  # 5 m above view 0; all toy-room views are at the same height
    w = far_poses(scene, T, [0.0, 0.2])
    assert [(x.frame, round(x.distance_m, 6)) for x in w] == [(1, 5.0)]
    assert far_poses(scene, T[:1], [0.7])[0].hole_frac == 0.7  # a big hole alone also warns


def test_help_shows_defaults(capsys):
    from presim.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices
    drive = sub["drive"].format_help()
    assert "(default: diff)" in " ".join(drive.split()) and "--max-memory SIZE" in drive
    render = " ".join(sub["render"].format_help().split())
    assert "(default: 4)" in render and "keeps the scene's aspect ratio" in render
    genbop = " ".join(sub["gen-bop"].format_help().split())
    assert "(default: 100)" in genbop and genbop.count("(default: 0.1)") <= 1  # one style, never repeated


# ---- gen-bop, sample-scene, envs -------------------------------------------------------------------
def test_gen_bop_refuses_huge_images_and_writes_nothing(capsys, tmp_path, toy):
    rc, _, err = run_cli(capsys, "gen-bop", toy, "--out", tmp_path / "bop", "--width", "100000",
                         "--height", "100000")
    assert rc == 1
    one_line_error(err, "--width/--height (100000x100000", "generating frames", "limit")
    assert not (tmp_path / "bop").exists()
    rc, _, err = run_cli(capsys, "gen-bop", toy, "--out", tmp_path / "bop", "--workers", "0")
    assert rc == 1 and one_line_error(err, "--workers")


def test_sample_scene_refuses_before_building(capsys, tmp_path):
    rc, _, err = run_cli(capsys, "sample-scene", tmp_path / "s", "--width", "20000", "--height", "20000")
    assert rc == 1 and one_line_error(err, "--width/--height/--frames (20000x20000, 60 frames)", "limit")
    rc, _, err = run_cli(capsys, "sample-scene", tmp_path / "s", "--frames", "0")
    assert rc == 1 and one_line_error(err, "--frames")
    assert not (tmp_path / "s").exists()


def test_env_refuses_bad_sizes(toy):
    from presim.limits import InputError
    from presim.sim.envs import PointNavEnv

    with pytest.raises(InputError, match="^width: must be at least 1"):
        PointNavEnv(toy, width=0)
    with pytest.raises(InputError, match=r"^width/height \(100000x100000"):
        PointNavEnv(toy, width=100000, height=100000)


def test_gym_ids_resolve_through_the_module_prefix_without_importing_presim(toy):
    """``gym.make("presim.sim.envs:ID")`` imports the module, which registers the ids: no import hook,
    and constructing the env applies the process settings (``presim.runtime.configure``)."""
    code = ("import os, sys, gymnasium as gym; assert 'presim' not in sys.modules; "
            f"env = gym.make('presim.sim.envs:PreSim-PointNav-v0', scene={str(toy)!r}, width=8, height=6); "
            "assert os.environ['OMP_WAIT_POLICY'] == 'PASSIVE'; "
            "print(gym.spec('PreSim-PointNav-v0').entry_point, gym.spec('PreSim-PointNavDiscrete-v0').kwargs)")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(env, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["presim.sim.envs:PointNavEnv", "{'discrete':", "True}"]


# ---- drive ----------------------------------------------------------------------------------------
def test_drive_says_when_the_route_ended(capsys, toy):
    rc, out, err = run_cli(capsys, "drive", toy, "--steps", "600", "--width", "16", "--height", "12")
    assert rc == 0
    steps = int(out.split("steps ")[1].split()[0])
    assert steps < 600
    assert f"note: the built-in route ended after {steps} of 600 steps (--steps 600 not reached)" in err


def test_drive_refuses_bad_sizes(capsys, toy):
    for args, words in ((["--width", "0"], ["--width"]), (["--dt", "nan"], ["--dt"]),
                        (["--width", "100000", "--height", "100000"], ["--width/--height", "one camera frame"])):
        rc, _, err = run_cli(capsys, "drive", toy, "--steps", "2", *args)
        assert rc == 1
        one_line_error(err, "presim drive: error:", *words)


def test_drive_native_viewer_without_display_is_one_line(capsys, toy, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    rc, _, err = run_cli(capsys, "drive", toy, "--steps", "2", "--width", "16", "--height", "12",
                         "--viewer", "native")
    assert rc == 1
    one_line_error(err, "--viewer native: no display", "--viewer web")


# ---- view ----------------------------------------------------------------------------------------
def test_view_refuses_a_file_that_is_not_a_recording(capsys, tmp_path):
    bad = tmp_path / "not-an-rrd.rrd"
    bad.write_bytes(b"hello, not a recording")
    rc, _, err = run_cli(capsys, "view", bad, "--web")
    assert rc == 1
    one_line_error(err, "not a rerun recording", "b'hell'")


def test_view_web_exits_130_on_ctrl_c(capsys, tmp_path, monkeypatch):
    import presim.outputs.viewer as viewer

    rrd = tmp_path / "a.rrd"
    rrd.write_bytes(b"RRF2" + bytes(16))
    monkeypatch.setattr(viewer, "rerun_executable", lambda: [sys.executable, "-c", "import time; time.sleep(60)"])

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(viewer, "wait_for_port", interrupt)
    assert main(["view", str(rrd), "--web"]) == 130


# ---- pose-eval -----------------------------------------------------------------------------------
def test_pose_results_reject_oversized_rows(tmp_path):
    from presim.pose.results import MAX_ROW_CHARS, read_bop_results

    good = "1,2,3,0.9," + "1 0 0 0 1 0 0 0 1" + ",10 20 30,-1"
    path = tmp_path / "r.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + good + "\n" + "1,2,3," + "9" * 200_000 + ",x,y,z\n"
                    + good + "\n" + '1,"unterminated\n')
    res = read_bop_results(path)
    assert [e.line for e in res.estimates] == [2, 4]
    assert [r.line for r in res.rejections] == [3, 5]
    assert res.rejections[0].reason == f"row of 200012 characters (at most {MAX_ROW_CHARS})"
    with pytest.raises(ValueError, match="line 3: row of 200012"):
        read_bop_results(path, strict=True)


# ---- refine --------------------------------------------------------------------------------------
def test_refine_marks_scene_json(tmp_path, toy):
    import shutil

    from presim.capture.store import load_scene, set_has_refined_depth

    dst = tmp_path / "s"
    shutil.copytree(toy, dst)
    assert json.loads((dst / "scene.json").read_text())["has_refined_depth"] is False
    np.save(dst / "depth_refined.npy", np.zeros((12, 120, 160), np.float32))
    set_has_refined_depth(dst)
    assert json.loads((dst / "scene.json").read_text())["has_refined_depth"] is True
    assert load_scene(dst).has_refined_depth
