"""The benchmark scripts run: every ``--help``, tiny runs of the cheap ones, the shared helpers.

Timings are not checked (meaningless at these sizes); what is checked is that each script still
matches the package's API, writes its JSON and keeps the shape other tools read (``bench_render.py``'s
``results["NAME WxH"]["fps_median"]``, the fingerprint's ``--save``/``--compare``).
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if p.name not in ("common.py", "__init__.py"))


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                       env={**os.environ, "PRESIM_NO_PROGRESS": "1"})
    assert p.returncode == 0, f"{' '.join(args)} failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}"
    return p


def test_every_script_has_help():
    """``--help`` of every script (and of every sub-command), all started at once: fast, since
    nothing heavy is imported before the arguments are parsed."""
    cmds = [[str(BENCH / s), "--help"] for s in SCRIPTS]
    subs = {"bench_sim.py": ("steps", "envs", "memory"), "bench_outputs.py": ("sinks", "teleop"),
            "bench_pose.py": ("metrics", "nets", "recipe"), "bench_depth.py": ("refine", "accuracy", "figure", "fusion"),
            "bench_generate.py": ("sample-scene", "gen-bop"), "check_render_quality.py": ("zoom", "lod")}
    cmds += [[str(BENCH / s), c, "--help"] for s, cs in subs.items() for c in cs]
    procs = [(c, subprocess.Popen([sys.executable, *c], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  cwd=ROOT)) for c in cmds]
    for c, p in procs:
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, f"{' '.join(c)}: {err[-2000:]}"
        assert "usage:" in out, f"{' '.join(c)} printed no usage"
    assert len(SCRIPTS) <= 12, f"benchmarks/ has {len(SCRIPTS)} scripts: fold overlapping ones together"


def test_scripts_share_one_module_and_name_no_machine_path():
    """Scripts import each other's code only through ``benchmarks.common``; no absolute paths."""
    for name in SCRIPTS + ["common.py"]:
        text = (BENCH / name).read_text()
        assert not re.search(r"^\s*(from|import) bench_|^\s*from (check|run)_", text, re.M), f"{name} imports a script"
        assert 'ROOT / "benchmarks"' not in text, f"{name} puts benchmarks/ on sys.path"
        assert not re.search(r"""["']/(work|home|mnt|data)/""", text), f"{name} names a machine path"
        if name not in ("run_all.py", "common.py"):
            assert "from benchmarks import common" in text, f"{name} does not use benchmarks.common"


def test_common_helpers(tmp_path):
    sys.path.insert(0, str(ROOT))
    from benchmarks import common

    assert common.parse_sizes("640x480,128x96") == [(640, 480), (128, 96)]
    with pytest.raises(SystemExit, match="WxH"):
        common.parse_size("640")
    assert common.APC.parent == ROOT.parent / "shared" / "data"
    scene, rects = common.synthetic_room(64, 48, views=4)
    poses = common.trajectory(scene, 5)
    T = scene.T_world_cam
    assert poses.shape == (5, 4, 4)
    np.testing.assert_allclose(poses[1][:3, 3], (T[1][:3, 3] + T[2][:3, 3]) / 2)
    np.testing.assert_allclose(poses[3][:3, :3], T[0][:3, :3])  # cycled: pair (0, 1) again
    calls = []
    times = common.alternate({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, 4)
    assert calls == ["a", "b", "b", "a", "a", "b", "b", "a"]  # ABBA
    assert len(times["a"]) == 4 and all(w >= 0 and c >= 0 for w, c in times["a"])
    ms, out = common.median_ms(lambda: 7, repeats=3)
    assert out == 7 and ms >= 0
    assert common.ratio(2.0, 1.0) == 2.0 and np.isnan(common.ratio(1.0, 0.0))
    common.write_json(tmp_path / "sub" / "r.json", {"x": np.float32(1.5), "a": np.arange(2)})
    assert json.loads((tmp_path / "sub" / "r.json").read_text()) == {"x": 1.5, "a": [0, 1]}
    assert not list((tmp_path / "sub").glob("*.tmp"))


@pytest.mark.slow
def test_fingerprint_save_and_compare(tmp_path):
    """The fingerprint's refine part, saved, then compared after one array changed: that array is
    named, every other one compares equal."""
    _run(str(BENCH / "check_outputs_identical.py"), "--save", str(tmp_path), "--parts", "refine")
    ref = np.load(tmp_path / "fingerprint.npz")
    assert {"refine__numba__depth", "refine__reference__cost"} <= set(ref.files)  # names old fingerprints use
    arrays = dict(ref)
    arrays["refine__numba__depth"] = arrays["refine__numba__depth"] + 1
    np.savez_compressed(tmp_path / "fingerprint.npz", **arrays)
    p = subprocess.run([sys.executable, str(BENCH / "check_outputs_identical.py"), "--compare", str(tmp_path),
                        "--parts", "refine"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 1, p.stderr[-2000:]
    assert "DIFF refine/numba/depth" in p.stdout and f"{len(arrays)} arrays compared, 1 differ" in p.stdout


CHEAP_RUNS = {  # tiny runs of the scripts that need no scene (a few CPU-seconds each)
    "pose-metrics": ("bench_pose.py", "metrics", "--quick"),
    "depth-refine": ("bench_depth.py", "refine", "--quick"),
    "sample-scene": ("bench_generate.py", "sample-scene", "--quick"),
    "sinks": ("bench_outputs.py", "sinks", "--quick", "--json", "OUT"),
    "run-all-list": ("run_all.py", "--quick", "--list"),
}


@pytest.mark.parametrize("name", list(CHEAP_RUNS))
def test_cheap_run(name, tmp_path):
    script, *args = CHEAP_RUNS[name]
    out = tmp_path / "out.json"
    p = _run(str(BENCH / script), *[str(out) if a == "OUT" else a for a in args])
    if "OUT" in args:
        assert json.loads(out.read_text())["per_sink_ms"]
    if script == "run_all.py":
        assert p.stdout.count("=====") >= 10


@pytest.mark.slow
def test_bench_render_quick(tmp_path):
    """bench_render.py's JSON keeps the shape the speed check of two trees reads."""
    out = tmp_path / "r.json"
    _run(str(BENCH / "bench_render.py"), "--quick", "--json", str(out), timeout=300)
    res = json.loads(out.read_text())["results"]
    assert list(res) == ["synthetic-room 64x48"]
    r = res["synthetic-room 64x48"]
    assert r["fps_median"] > 0 and r["frames"] == 3 and r["speedup_vs_naive"] > 0
