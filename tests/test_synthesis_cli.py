"""``presim render`` end to end on a small saved synthetic scene."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from presim.capture.store import save_scene
from presim.cli import main
from presim.geometry import Intrinsics, pose_to_tum
from presim.testing import rect_scene as S


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    import os

    os.environ["PRESIM_NO_PROGRESS"] = "1"
    K = Intrinsics.from_fov(160, 120, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(5), K)
    return save_scene(scene, tmp_path_factory.mktemp("s") / "room")


def test_render_frame_pose_and_trajectory(scene_dir, tmp_path):
    out = tmp_path / "r1"
    assert main(["render", str(scene_dir), "--frame", "2", "--out", str(out)]) == 0
    color = cv2.imread(str(out / "frame-000000.color.png"))
    depth = cv2.imread(str(out / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    valid = cv2.imread(str(out / "frame-000000.valid.png"), cv2.IMREAD_UNCHANGED)
    assert color.shape == (120, 160, 3) and depth.dtype == np.uint16 and valid.shape == (120, 160)
    # Rendering a captured pose reproduces that frame's depth (mm) where synthesized.
    from presim.capture.store import load_scene

    sc = load_scene(scene_dir)
    d_true = sc.frames.load(2)[1]
    m = valid > 0
    assert m.mean() > 0.95
    err = np.abs(depth[m] / 1000.0 - d_true[m])
    # Exact up to mm rounding except a few pixels on layer boundaries, where a layer's switching
    # median may take a neighbour's value of the same surface (a known trait of per-layer filling).
    assert np.median(err) < 0.0006 and np.mean(err > 0.002) < 0.01
    summary = json.loads((out / "render.json").read_text())
    assert summary["num_frames"] == 1 and summary["config"]["num_layers"] == 4

    # One pose on the command line, another resolution and layer count, no fill.
    q = " ".join(f"{x:.9f}" for x in pose_to_tum(sc.T_world_cam[1]))
    out2 = tmp_path / "r2"
    assert main(["render", str(scene_dir), "--pose", q, "--out", str(out2), "--width", "200", "--height", "150",
                 "--layers", "2", "--no-fill"]) == 0
    c2 = cv2.imread(str(out2 / "frame-000000.color.png"))
    assert c2.shape == (150, 200, 3)

    # A TUM trajectory of 3 poses.
    tum = tmp_path / "traj.txt"
    tum.write_text("# stamp x y z qx qy qz qw\n" + "".join(
        f"{i * 0.1} " + " ".join(f"{x:.9f}" for x in pose_to_tum(sc.T_world_cam[i])) + "\n" for i in range(3)))
    out3 = tmp_path / "r3"
    assert main(["render", str(scene_dir), "--poses", str(tum), "--out", str(out3), "--min-view-gain", "0"]) == 0
    assert len(list(out3.glob("*.color.png"))) == 3 and (out3 / "trajectory_tum.txt").is_file()
    assert not list(out3.glob(".*.tmp"))  # atomic writes leave no temporaries


def test_render_bad_input_is_a_clear_error(scene_dir, tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope"), "--frame", "0", "--out", str(tmp_path / "o")]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["render", str(scene_dir), "--frame", "99", "--out", str(tmp_path / "o")]) == 1
    assert "frames 0..4" in capsys.readouterr().err
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3\n")
    assert main(["render", str(scene_dir), "--poses", str(bad), "--out", str(tmp_path / "o")]) == 1
    assert "bad.txt:1" in capsys.readouterr().err
    assert main(["render", str(scene_dir), "--pose", "1 2 3", "--out", str(tmp_path / "o")]) == 1
    assert "7 numbers" in capsys.readouterr().err
    for bad_gain in ("1", "-0.1", "nan"):
        assert main(["render", str(scene_dir), "--frame", "0", "--min-view-gain", bad_gain,
                     "--out", str(tmp_path / "o")]) == 1
        err = capsys.readouterr().err
        assert "--min-view-gain must be in [0, 1)" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_render_torch_backend_renders_batches_on_cpu(scene_dir, tmp_path, capsys):
    """--backend torch: 5 poses in batches of 2 (2 + 2 + 1) through Renderer.render_batch; each
    captured pose reproduces its frame's depth like the numba backend."""
    from presim.capture.store import load_scene

    sc = load_scene(scene_dir)
    tum = tmp_path / "traj.txt"
    tum.write_text("".join(f"{i * 0.1} " + " ".join(f"{x:.9f}" for x in pose_to_tum(sc.T_world_cam[i])) + "\n"
                           for i in range(5)))
    out = tmp_path / "rb"
    assert main(["render", str(scene_dir), "--poses", str(tum), "--out", str(out), "--backend", "torch",
                 "--batch-size", "2"]) == 0
    summary = json.loads((out / "render.json").read_text())
    assert summary["num_frames"] == 5 and summary["perf"]["backend"] == "torch"
    assert all(1 <= v <= summary["config"]["max_views"] for v in summary["views_used"])
    for i in range(5):
        depth = cv2.imread(str(out / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
        valid = cv2.imread(str(out / f"frame-{i:06d}.valid.png"), cv2.IMREAD_UNCHANGED) > 0
        err = np.abs(depth[valid] / 1000.0 - sc.frames.load(i)[1][valid])
        assert valid.mean() > 0.95 and np.median(err) < 0.0006
    assert main(["render", str(scene_dir), "--frame", "0", "--out", str(tmp_path / "o"), "--backend",
                 "torch", "--batch-size", "0"]) == 1
    assert "--batch-size" in capsys.readouterr().err
