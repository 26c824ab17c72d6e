"""End to end: the README's main command on a small built-in scene (slow; runs in CI)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from presim.cli import main


@pytest.mark.slow
def test_demo_builds_drives_records_views_and_writes_bop(tmp_path, capsys):
    out = tmp_path / "demo"
    # A smaller sample scene first, so the demo reuses it (it only builds one when missing).
    assert main(["sample-scene", str(out / "scene"), "--frames", "12", "--width", "160", "--height", "120"]) == 0
    rc = main(["demo", str(out), "--steps", "12", "--bop-frames", "3", "--bop-size", "160", "90"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "Done. Outputs in" in text
    assert (out / "drive" / "recording.mcap").stat().st_size > 0
    assert (out / "drive.rrd").stat().st_size > 0
    gt = json.loads((out / "bop/train/000000/scene_gt.json").read_text())
    assert len(gt) == 3
    summary_gt = json.loads((out / "pose_eval_gt/report.json").read_text())
    summary_noisy = json.loads((out / "pose_eval_gt_noisy/report.json").read_text())
    assert summary_gt["overall"]["auc_add_s"] == pytest.approx(1.0)
    # 5 mm / 2 deg noise must cost something, but not everything.
    assert 0.3 < summary_noisy["overall"]["auc_add_s"] < 0.999
    assert np.isfinite(summary_noisy["overall"]["mean_proj_px"]) and summary_noisy["overall"]["mean_proj_px"] > 0
