"""`presim import` / `presim info` end to end, and scene_info on a written capture."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import synth_frames, write_kinfu, write_tum  # noqa: E402

from presim.capture.info import format_info, scene_info  # noqa: E402
from presim.capture.store import load_scene  # noqa: E402
from presim.cli import main  # noqa: E402


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def test_import_and_info_cli(tmp_path, capsys):
    f = synth_frames(n=5)
    src = write_kinfu(tmp_path / "cap", f)
    dst = tmp_path / "scene"
    assert main(["import", str(src), str(dst), "--every", "2", "--no-floor"]) == 0
    out = capsys.readouterr().out
    assert "frames      3" in out and "resolution  40x30" in out
    s = load_scene(dst)
    assert s.frame_ids == ["frame-000000", "frame-000002", "frame-000004"]
    assert any("floor alignment disabled" in n for n in s.meta.notes)
    # exists -> error without --overwrite, success with it
    assert main(["import", str(src), str(dst)]) == 1
    assert "already exists" in capsys.readouterr().err
    assert main(["import", str(src), str(dst), "--overwrite", "--max-frames", "2", "--format", "kinfu",
                 "--gravity", "0", "0", "-1", "--no-floor"]) == 0
    capsys.readouterr()
    s = load_scene(dst)
    assert len(s) == 2 and np.allclose(s.gravity_world, [0, 0, -1])
    assert main(["info", str(dst), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_frames"] == 2 and info["resolution_wh"] == [40, 30]
    assert info["trajectory_length_m"] == pytest.approx(np.linalg.norm(f.T_world_cam[1, :3, 3] - f.T_world_cam[0, :3, 3]))
    assert info["depth_coverage"]["mean_valid_frac"] == pytest.approx((f.depth_mm[:2] > 0).mean())
    assert info["refined_depth"] is False and info["floor"] is None
    assert main(["info", str(dst)]) == 0
    text = capsys.readouterr().out
    for key in ("frames", "resolution", "intrinsics", "depth", "extent", "trajectory", "floor", "gravity",
                "objects", "refined"):
        assert f"\n{key}" in "\n" + text, key


def test_cli_bad_input_one_line_error(tmp_path, capsys):
    src = write_tum(tmp_path / "tum", synth_frames(n=2))
    (src / "depth.txt").write_text("1305031102.005 depth/missing.png\n")
    assert main(["import", str(src), str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("presim import: error:") and "missing.png" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()
    assert main(["info", str(tmp_path / "nothing")]) == 1
    assert "not a PreSim scene" in capsys.readouterr().err
    assert main(["import", str(tmp_path / "nope"), str(tmp_path / "out")]) == 1
    assert "capture not found" in capsys.readouterr().err


def test_info_on_real_scene_with_objects(shared_data, tmp_path, capsys):
    src = shared_data("ycbv_2frames")
    assert main(["import", str(src), str(tmp_path / "y")]) == 0
    capsys.readouterr()
    info = scene_info(load_scene(tmp_path / "y"))
    assert len(info["objects"]) == 7 and info["floor"] is None
    assert info["depth_coverage"]["sampled_frames"] == 2
    assert "no floor found" in format_info(info)
