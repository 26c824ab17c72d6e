"""scripts/pose_runs_table.py: mean ± sample std over seeds of pose-eval reports (known answers)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("pose_runs_table", ROOT / "scripts" / "pose_runs_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _report(auc: float, obj_auc: float) -> dict:
    return {"overall": {"auc_add_s": auc, "acc_add_s_2cm": 0.25, "acc_add_s_01d": auc / 2},
            "per_object": {"1": {"auc_add_s": obj_auc, "symmetric": False},
                           "2": {"auc_add_s": 1.0, "symmetric": True}}}


def test_mean_and_sample_std_over_seeds(tmp_path, capsys):
    mod = _module()
    assert mod.mean_std([0.5, 0.7]) == "0.600 ± 0.141"     # sample std: sqrt(0.02) = 0.1414
    assert mod.mean_std([0.25]) == "0.250"
    for i, (a, o) in enumerate([(0.5, 0.1), (0.7, 0.3)]):
        d = tmp_path / f"m_s{i}_eval"
        d.mkdir()
        (d / "report.json").write_text(json.dumps(_report(a, o)))
    assert mod.main([f"M={tmp_path}/m_s?_eval"]) == 0
    out = capsys.readouterr().out
    assert "| M | 2 | 0.600 ± 0.141 | 0.250 ± 0.000 | 0.300 ± 0.071 |" in out
    assert "| M | 0.200 ± 0.141 | 1.000 ± 0.000 |" in out and "2 (sym)" in out
    assert mod.main([f"M={tmp_path}/none_*"]) == 2


def test_visibility_curve_is_the_mean_over_runs_and_skips_empty_bins():
    mod = _module()
    vis = lambda a: {"bin_edges": [0.0, 0.5, 1.0], "n": [0, 4], "acc_add_s_01d": [None, a]}  # noqa: E731
    edges, n, vals = mod.visibility_curve([{"visibility": vis(0.25)}, {"visibility": vis(0.75)}])
    assert edges == [0.0, 0.5, 1.0] and n == [0, 4] and vals == [None, 0.5]
