"""presim sim2real depth (issue 15): metric known answers, the capture/test split, the synthesized
poses, the no-leak guarantee, an end-to-end run of the three arms on a tiny synthetic room, resume
and the one-line errors of the CLI."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from presim.capture.scene import ArrayFrameSource
from presim.cli import main
from presim.evaluation.sim2real import depth_metrics, pose_distance, split_capture, synth_poses
from presim.evaluation.sim2real.experiment import (ARMS, DepthExperimentConfig, build_training_set,
                                                  capture_subscene, run_depth_experiment)
from presim.geometry import look_at
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

TINY = dict(capture_every=2, synth=4, steps=3, seeds=(0,), size_wh=(64, 48), batch_real=2, batch_synth=2,
            width=8, eval_points=1)


# ---- metrics: hand-computed values --------------------------------------------------------------
def test_metrics_match_hand_computed_values():
    pred = np.array([[1.0, 2.0], [3.0, 4.0]])
    gt = np.array([[1.0, 4.0], [0.0, 2.0]])  # (1,0) invalid -> pixels (1|1), (2|4), (4|2)
    m = depth_metrics(pred, gt)
    assert m["n_pixels"] == 3
    assert m["rms"] == pytest.approx(np.sqrt((0 + 4 + 4) / 3))
    assert m["absrel"] == pytest.approx((0 + 0.5 + 1.0) / 3)
    assert m["delta1"] == pytest.approx(1 / 3)  # ratios 1, 2, 2


def test_metrics_clip_prediction_and_drop_far_ground_truth():
    m = depth_metrics(np.array([0.0, 20.0, 1.2]), np.array([0.5, 12.0, 1.0]), max_depth_m=10.0)
    # 12 m > max -> dropped; pred 0 clipped to 0.1 -> |0.1 - 0.5| = 0.4; |1.2 - 1.0| = 0.2
    assert m["n_pixels"] == 2
    assert m["rms"] == pytest.approx(np.sqrt((0.16 + 0.04) / 2))
    assert m["absrel"] == pytest.approx((0.4 / 0.5 + 0.2 / 1.0) / 2)
    assert m["delta1"] == pytest.approx(0.5)  # 0.5/0.1 = 5 fails, 1.2 passes


# ---- split and poses ----------------------------------------------------------------------------
def _line_poses(n: int, step_m: float = 0.05, yaw_deg: float = 0.0) -> np.ndarray:
    out = []
    for k in range(n):
        a = np.radians(yaw_deg * k)
        eye = np.array([step_m * k, 0.0, 1.0])
        out.append(look_at(eye, eye + np.array([np.cos(a), np.sin(a), 0.0])))
    return np.stack(out)


def test_pose_distance_known_answers():
    P = _line_poses(2, step_m=0.3, yaw_deg=90.0)
    t, r = pose_distance(P, P)
    assert t[0, 1] == pytest.approx(0.3) and r[0, 1] == pytest.approx(90.0, abs=1e-6)
    assert t[1, 1] == 0 and r[1, 1] == pytest.approx(0.0, abs=1e-5)


def test_split_every_nth_and_terciles():
    P = _line_poses(10)
    s = split_capture(P, 3)
    assert s.capture_idx.tolist() == [0, 3, 6, 9]
    assert s.test_idx.tolist() == [1, 2, 4, 5, 7, 8]
    assert s.trans_m == pytest.approx(np.full(6, 0.05))  # every test frame is one step from a capture
    assert s.nearest_capture.tolist() == [0, 3, 3, 6, 6, 9]
    assert np.bincount(s.bin_of).tolist() == [2, 2, 2]
    P2 = _line_poses(13, step_m=0.01)
    s2 = split_capture(P2, 6)  # capture 0, 6, 12; test distances 1,2,3,3,2,1 steps (twice)
    far = s2.test_idx[s2.bin_of == 2]
    # 1 step: 1,5,7,11; 2 steps: 2,4,8,10; 3 steps: 3,9 -> terciles of 10 (4/3/3): near = the 1-step
    # frames, far = both 3-step frames + one 2-step frame (which one is floating-point rounding)
    assert sorted(s2.test_idx[s2.bin_of == 0].tolist()) == [1, 5, 7, 11]
    assert len(far) == 3 and {3, 9} <= set(far.tolist()) and len(set(far.tolist()) & {2, 4, 8, 10}) == 1
    assert s2.rot_deg == pytest.approx(np.zeros(10), abs=1e-5)


@pytest.mark.parametrize("n, msg", [(1, "leaves no test frames"), (10, "need >= 2"), (11, "need >= 2")])
def test_split_rejects_bad_capture_every(n, msg):
    with pytest.raises(ValueError, match=msg):
        split_capture(_line_poses(10), n)


def test_synth_poses_are_seeded_rigid_and_near_the_capture_path():
    P = _line_poses(5, step_m=0.5, yaw_deg=10.0)
    a, b = synth_poses(P, 50, seed=3), synth_poses(P, 50, seed=3)
    assert np.array_equal(a, b) and not np.array_equal(a, synth_poses(P, 50, seed=4))
    R = a[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    c = a[:, :3, 3]
    assert np.all(np.abs(c[:, 2] - 1.0) <= 0.03 + 1e-9)  # robot height: capture height +- 3 cm
    assert np.all((c[:, 0] >= -0.15 - 1e-9) & (c[:, 0] <= 2.0 + 0.15 + 1e-9))
    assert np.all(np.abs(c[:, 1]) <= 0.15 + 1e-9)
    with pytest.raises(ValueError, match="--synth"):
        synth_poses(P, 0, seed=0)


# ---- the split never leaks ----------------------------------------------------------------------
class _RecordingSource:
    def __init__(self, base):
        self.base, self.loaded = base, []

    def __len__(self):
        return len(self.base)

    def load(self, idx):
        self.loaded.append(int(idx))
        return self.base.load(idx)


def _toy(num_views: int = 12):
    return build_toy_room(ToyRoomConfig(num_views=num_views, width=96, height=72))


def _poisoned(scene, test_idx, seed=1):
    """The same scene with every test frame's pixels and pose replaced by junk."""
    rng = np.random.default_rng(seed)
    colors = np.stack([scene.frames.load(i)[0] for i in range(len(scene))])
    depths = np.stack([scene.frames.load(i)[1] for i in range(len(scene))])
    T = scene.T_world_cam.copy()
    for i in test_idx:
        colors[i] = rng.integers(0, 256, colors[i].shape, dtype=np.uint8)
        depths[i] = rng.uniform(0.5, 5.0, depths[i].shape).astype(np.float32)
        T[i] = look_at(rng.uniform(0, 4, 3), rng.uniform(0, 4, 3) + 5.0)
    return dataclasses.replace(scene, frames=ArrayFrameSource(colors, depths), T_world_cam=T)


def test_training_set_and_renderer_scene_see_capture_frames_only():
    scene = _toy()
    rec = _RecordingSource(scene.frames)
    scene = dataclasses.replace(scene, frames=rec)
    cfg = DepthExperimentConfig(**TINY)
    split = split_capture(scene.T_world_cam, cfg.capture_every)
    sub = capture_subscene(scene, split)
    assert sub.frame_ids == [scene.frame_ids[i] for i in split.capture_idx]
    assert np.array_equal(sub.T_world_cam, scene.T_world_cam[split.capture_idx])
    assert sub.depth_refined is None and sub.points is None and sub.floor is None
    data = build_training_set(sub, cfg)
    assert set(rec.loaded) <= set(split.capture_idx.tolist())  # no test frame's pixels were read
    # Junk in every test frame (pixels and poses) changes nothing an arm or the renderer sees.
    bad = _poisoned(scene, split.test_idx)
    data2 = build_training_set(capture_subscene(bad, split_capture(bad.T_world_cam, 2)), cfg)
    for f in ("real_rgb", "real_depth", "synth_poses", "synth_rgb", "synth_depth"):
        assert np.array_equal(getattr(data, f), getattr(data2, f)), f
    assert (data.synth_depth > 0).mean() > 0.5  # the views were really synthesized


@pytest.mark.slow  # refinement kernels compile on first use (minutes on the loaded 2-core VM)
def test_refined_capture_depth_uses_capture_frames_only(tmp_path):
    from presim.evaluation.sim2real.experiment import refine_capture

    scene = _toy()
    split = split_capture(scene.T_world_cam, 2)
    sub = refine_capture(capture_subscene(scene, split), tmp_path / "a")
    assert sub.depth_refined.shape == (6, 72, 96)
    bad = _poisoned(scene, split.test_idx)
    sub2 = refine_capture(capture_subscene(bad, split_capture(bad.T_world_cam, 2)), tmp_path / "b")
    assert np.array_equal(np.asarray(sub.depth_refined), np.asarray(sub2.depth_refined))
    gt = np.stack([scene.frames.load(int(i))[1] for i in split.capture_idx])
    assert np.median(np.abs(np.asarray(sub.depth_refined) - gt)[gt > 0]) < 0.01  # exact toy depth kept


# ---- end to end on a tiny synthetic room --------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    scene = _toy()
    out = tmp_path_factory.mktemp("s2r") / "run"
    cfg = DepthExperimentConfig(**TINY)
    return scene, cfg, out, run_depth_experiment(scene, cfg, out)


@pytest.mark.slow  # ~10 s each unloaded; the first one pays torch/numba/matplotlib start-up
def test_three_arms_end_to_end_give_finite_metrics_and_all_outputs(tiny_run):
    _, _, out, summary = tiny_run
    assert set(summary) == {"arms", "bins", "config", "distance_curve"}
    assert set(summary["arms"]) == set(ARMS)
    # 6 test frames -> 3 fine bins = the terciles (same ranking): pooling the stored per-frame
    # errors must give the terciles' RMS of every arm and seed
    curve = summary["distance_curve"]
    assert [b["n_frames"] for b in curve["bins"]] == [2, 2, 2]
    for arm in ARMS:
        got = curve["arms"][arm]["seeds"]["0"]
        want = [summary["arms"][arm]["seeds"]["0"]["bins"][b]["rms"] for b in ("near", "mid", "far")]
        assert got == pytest.approx(want, rel=1e-9), arm
    for arm in ARMS:
        s = summary["arms"][arm]
        for k in ("rms", "absrel", "delta1"):
            assert np.isfinite(s[k]), (arm, k)
            for b in ("near", "mid", "far"):
                assert np.isfinite(s["bins"][b][k])
    assert sum(summary["bins"][b]["n_frames"] for b in ("near", "mid", "far")) == summary["config"]["n_test"] == 6
    for f in ("summary.json", "report.md", "learning_curves.png", "examples.png", "timing.json",
              "rms_vs_distance.png"):
        assert (out / f).stat().st_size > 0
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(summary))
    report = (out / "report.md").read_text()
    assert "| capture+synth |" in report and "capture+synth vs capture, overall RMS" in report
    assert summary["config"]["recipe"] == "custom"


@pytest.mark.slow  # ~10 s each unloaded; the first one pays torch/numba/matplotlib start-up
def test_test_frames_do_not_change_training(tiny_run, tmp_path):
    """End to end: junk test frames give identical training losses in every arm (only the metrics
    differ)."""
    scene, cfg, out, summary = tiny_run
    split = split_capture(scene.T_world_cam, cfg.capture_every)
    bad = _poisoned(scene, split.test_idx)
    run_depth_experiment(bad, cfg, tmp_path / "bad")
    for arm in ("capture", "capture_synth", "synth"):
        a = json.loads((out / "runs" / f"{arm}-seed0.json").read_text())
        b = json.loads((tmp_path / "bad" / "runs" / f"{arm}-seed0.json").read_text())
        assert a["train_loss"] == b["train_loss"], arm
        assert a["overall"] != b["overall"]


@pytest.mark.slow  # ~10 s each unloaded; the first one pays torch/numba/matplotlib start-up
def test_resume_recomputes_only_missing_runs(tiny_run):
    scene, cfg, out, summary = tiny_run
    runs = out / "runs"
    keep = {p.name: p.stat().st_mtime_ns for p in runs.glob("*.json")}
    (runs / "synth-seed0.json").unlink()  # interrupted after the npz, before the json
    again = run_depth_experiment(scene, cfg, out)
    assert {p.name for p in runs.glob("*.json")} == set(keep)
    for name, t in keep.items():
        if name != "synth-seed0.json":
            assert (runs / name).stat().st_mtime_ns == t, name
    assert again["arms"]["synth"]["rms"] == pytest.approx(summary["arms"]["synth"]["rms"])
    assert again["arms"]["capture"] == summary["arms"]["capture"]


# ---- CLI: one-line errors -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def saved_toy(tmp_path_factory):
    from presim.capture.store import save_scene

    root = tmp_path_factory.mktemp("scenes")
    scene = _toy(num_views=8)
    good = save_scene(scene, root / "toy")
    colors = np.stack([scene.frames.load(i)[0] for i in range(len(scene))])
    nodepth = dataclasses.replace(scene, frames=ArrayFrameSource(colors, np.zeros((8, 72, 96), np.float32)))
    return good, save_scene(nodepth, root / "nodepth")


@pytest.mark.parametrize("extra, msg", [
    (["--capture-every", "2", "--synth", "0"], "--synth must be >= 1"),
    (["--capture-every", "8", "--synth", "4"], "leaves 1 capture frame"),
    (["--capture-every", "1", "--synth", "4"], "leaves no test frames"),
])
def test_cli_bad_input_is_one_line(saved_toy, tmp_path, capsys, extra, msg):
    good, _ = saved_toy
    assert main(["sim2real", "depth", str(good), "--out", str(tmp_path / "o"), *extra]) == 1
    err = capsys.readouterr().err.strip()
    assert msg in err and "\n" not in err and "Traceback" not in err


def test_cli_scene_without_depth_is_one_line(saved_toy, tmp_path, capsys):
    _, nodepth = saved_toy
    rc = main(["sim2real", "depth", str(nodepth), "--capture-every", "2", "--synth", "4",
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "no depth" in err and "\n" not in err
    assert main(["sim2real", "depth", str(tmp_path / "missing"), "--capture-every", "2", "--synth", "4",
                 "--out", str(tmp_path / "o")]) == 1
    assert "not found" in capsys.readouterr().err


# ---- schedule, batches, labels, fingerprint (issue 15, convergence round) -----------------------
def test_lr_factor_warmup_then_cosine_known_answers():
    from presim.evaluation.sim2real.experiment import lr_factor

    cfg = DepthExperimentConfig(capture_every=2, synth=4, steps=105, warmup_frac=5 / 105, min_lr_frac=0.01)
    # 5 warm-up steps: 1/5 .. 5/5; then cosine over steps 5..104 (span 99) from 1 down to 0.01
    assert [lr_factor(k, cfg) for k in range(5)] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0])
    assert lr_factor(5, cfg) == pytest.approx(1.0)
    assert lr_factor(104, cfg) == pytest.approx(0.01)
    mid = 5 + 99 / 2  # half way: 0.01 + 0.99 * 0.5 * (1 + cos(pi / 2)) = 0.505
    assert lr_factor(int(mid), cfg) == pytest.approx(0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * 49 / 99)))
    assert lr_factor(60, dataclasses.replace(cfg, schedule="constant")) == 1.0
    with pytest.raises(ValueError, match="--schedule"):
        dataclasses.replace(cfg, schedule="step")


def test_batch_rows_share_real_samples_and_flips_across_arms():
    from presim.evaluation.sim2real.experiment import batch_rows

    cfg = DepthExperimentConfig(capture_every=2, synth=4, steps=50, batch_real=3, batch_synth=2)
    a = batch_rows("capture", 7, 5, 11, cfg)
    b = batch_rows("capture+synth", 7, 5, 11, cfg)
    c = batch_rows("synth", 7, 5, 11, cfg)
    assert a.shape == (50, 3) and b.shape == (50, 5) and c.shape == (50, 2)
    assert np.array_equal(b, np.concatenate([a, c], axis=1))  # (b) = (a)'s real batch + (c)'s
    assert a.min() >= 0 and a.max() < 10  # pool rows: real 0..4, real flipped 5..9
    assert c.min() >= 10 and c.max() < 10 + 22  # synth 10..20, synth flipped 21..31
    assert (a >= 5).any() and (a < 5).any() and (c >= 21).any() and (c < 21).any()  # both flips drawn
    assert not np.array_equal(a, batch_rows("capture", 8, 5, 11, cfg))


def test_capture_labels_rendered_or_sensor():
    scene = _toy()
    split = split_capture(scene.T_world_cam, 2)
    sub = capture_subscene(scene, split)
    cfg = DepthExperimentConfig(**TINY)
    ren = build_training_set(sub, cfg)
    sen = build_training_set(sub, dataclasses.replace(cfg, real_labels="sensor"))
    assert np.array_equal(sen.real_depth, sen.sensor_depth)  # sensor labels: the resized sensor depth
    assert np.array_equal(ren.sensor_depth, sen.sensor_depth)
    # rendered at the capture frame's own pose: the toy depth is exact, so the labels agree with the
    # sensor where both exist, and cover about as much of the image as the synthesized labels
    both = (ren.real_depth > 0) & (sen.real_depth > 0)
    assert both.mean() > 0.5
    assert np.median(np.abs(ren.real_depth - sen.real_depth)[both]) < 0.02
    assert abs((ren.real_depth > 0).mean() - (ren.synth_depth > 0).mean()) < 0.2


def test_out_dir_of_another_configuration_or_code_is_refused(tmp_path, monkeypatch):
    import presim.evaluation.sim2real.experiment as ex

    scene = _toy()
    cfg = DepthExperimentConfig(**TINY)
    fp = cfg.fingerprint(scene)
    assert fp == dataclasses.replace(cfg, seeds=(0, 1), threads=2).fingerprint(scene)  # seeds/threads resume
    assert fp != dataclasses.replace(cfg, lr=2e-3).fingerprint(scene)
    monkeypatch.setattr(ex, "EXPERIMENT_VERSION", ex.EXPERIMENT_VERSION + 1)
    assert fp != cfg.fingerprint(scene)  # a new code version never resumes into old results
    monkeypatch.undo()
    moved = dataclasses.replace(scene, T_world_cam=scene.T_world_cam.copy())
    moved.T_world_cam[0, 0, 3] += 0.01
    assert fp != cfg.fingerprint(moved)  # other poses (e.g. --scene-poses refined)
    out = tmp_path / "run"
    out.mkdir()
    (out / "runs").mkdir()
    (out / "runs" / "capture-seed0.json").write_text("{}")
    (out / "experiment.json").write_text(json.dumps({"fingerprint": "0123456789abcdef"}))
    with pytest.raises(ex.ExperimentMismatch, match="another configuration"):
        run_depth_experiment(scene, cfg, out)
    assert (out / "runs" / "capture-seed0.json").exists()  # refused: nothing deleted
    ex._claim_dir(out, cfg, fp, restart=True)
    assert not (out / "runs" / "capture-seed0.json").exists()
    assert json.loads((out / "experiment.json").read_text())["fingerprint"] == fp
    ex._claim_dir(out, cfg, fp, restart=False)  # same fingerprint: accepted (resume)


def test_cli_scene_poses_default_given(saved_toy, tmp_path, capsys):
    good, _ = saved_toy
    rc = main(["sim2real", "depth", str(good), "--capture-every", "2", "--synth", "4", "--scene-poses", "refined",
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "no refined poses" in err and "\n" not in err


# ---- recipes, finer binning, capture-density sweep, streamed frames (issue 46) -------------------
def test_recipes_default_and_quick():
    from presim.evaluation.sim2real.experiment import RECIPES, recipe_config, recipe_name

    d, q = recipe_config("default", 9), recipe_config("quick", 9)
    assert (d.size_wh, d.steps, d.synth, d.width) == ((160, 120), 1200, 1000, 16)
    assert (q.size_wh, q.steps, q.synth, q.width, q.batch_real, q.batch_synth) == ((64, 48), 1000, 400, 16, 8, 8)
    assert d == DepthExperimentConfig(capture_every=9, synth=1000)  # field defaults = the default recipe
    assert recipe_name(d) == "default" and recipe_name(q) == "quick"
    assert recipe_name(dataclasses.replace(q, seeds=(4,), threads=2)) == "quick"  # not part of a recipe
    assert recipe_name(dataclasses.replace(q, steps=3)) == "custom"
    assert recipe_config("quick", 9, steps=None, synth=7).synth == 7  # None = the recipe's value
    assert set(RECIPES) == {"default", "quick"}
    with pytest.raises(ValueError, match="recipe must be one of"):
        recipe_config("huge", 9)


def test_distance_curve_pools_per_frame_errors_by_distance():
    from presim.evaluation.sim2real.report import distance_curve, fine_bin_count

    dist = np.array([0.5, 0.1, 0.3, 0.2, 0.4, 0.6])
    sq = [[4.0, 1.0, 0.0, 9.0, 1.0, 16.0], [0.0] * 6]
    n = [[1, 1, 1, 1, 1, 4], [1] * 6]
    runs = {"capture": [{"seed": s, "per_frame": {"sq_sum": sq[s], "n_pixels": n[s]}} for s in (0, 1)]}
    c = distance_curve(runs, dist, n_bins=3)
    # ranks by distance: (0.1, 0.2) (0.3, 0.4) (0.5, 0.6) -> frames (1, 3) (2, 4) (0, 5)
    assert [b["n_frames"] for b in c["bins"]] == [2, 2, 2]
    assert [b["d_median"] for b in c["bins"]] == pytest.approx([0.15, 0.35, 0.55])
    assert c["arms"]["capture"]["seeds"]["0"] == pytest.approx([np.sqrt(10 / 2), np.sqrt(1 / 2), np.sqrt(20 / 5)])
    assert c["arms"]["capture"]["rms"][0] == pytest.approx(np.sqrt(5) / 2)  # mean over the two seeds
    assert c["arms"]["capture"]["rms_std"][0] == pytest.approx(np.std([np.sqrt(5), 0.0], ddof=1))
    assert fine_bin_count(6) == 3 and fine_bin_count(160) == 10 and fine_bin_count(40) == 8
    with pytest.raises(ValueError, match="n_bins"):
        distance_curve(runs, dist, n_bins=7)


def test_crossover_known_answers():
    from presim.evaluation.sim2real.sweep import crossover, parse_capture_every_list

    c = crossover([50, 10, 25], [0.15, -0.09, 0.05])  # any order: sorted by density
    assert c["kind"] == "between" and c["between"] == [10, 25]
    assert c["capture_every"] == pytest.approx(10 + 15 * 0.09 / 0.14)
    assert crossover([10, 25], [0.1, 0.2])["kind"] == "helps_everywhere"
    assert crossover([10, 25], [-0.1, 0.0])["kind"] == "hurts_everywhere"
    assert crossover([10, 25, 50], [0.1, -0.05, 0.2])["kind"] == "mixed"
    assert crossover([10, 25], [0.1, -0.1])["capture_every"] == pytest.approx(17.5)
    assert parse_capture_every_list("50, 10,25") == (10, 25, 50)
    for bad in ("10", "1,5", "a,b"):
        with pytest.raises(ValueError, match="--sweep-capture-every"):
            parse_capture_every_list(bad)


def test_release_frames_keeps_memmapped_frames_readable(tmp_path):
    from presim.capture.scene import release_frames

    c = np.lib.format.open_memmap(tmp_path / "c.npy", mode="w+", dtype=np.uint8, shape=(3, 4, 5, 3))
    d = np.lib.format.open_memmap(tmp_path / "d.npy", mode="w+", dtype=np.float32, shape=(3, 4, 5))
    c[:] = np.arange(c.size, dtype=np.uint64).reshape(c.shape) % 251
    d[:] = np.arange(d.size, dtype=np.float32).reshape(d.shape)
    c.flush(), d.flush()
    src = ArrayFrameSource(np.load(tmp_path / "c.npy", mmap_mode="r"), np.load(tmp_path / "d.npy", mmap_mode="r"))
    before = [np.array(a) for a in src.load(2)]
    release_frames(src)
    assert all(np.array_equal(x, y) for x, y in zip(before, src.load(2)))  # mapped in again
    mem = ArrayFrameSource(np.array(c), np.array(d))
    release_frames(mem)  # in-memory arrays: nothing to drop
    release_frames(object())  # a source without release(): a no-op
    assert np.array_equal(mem.load(1)[1], d[1])


@pytest.mark.slow  # two tiny experiments (~10 s unloaded)
def test_capture_sweep_writes_gain_table_plot_and_crossover(tmp_path):
    from presim.evaluation.sim2real.sweep import run_capture_sweep

    scene = _toy()
    res = run_capture_sweep(scene, DepthExperimentConfig(**TINY), (2, 3), tmp_path / "sw")
    assert [r["capture_every"] for r in res["rows"]] == [2, 3]
    assert [r["n_capture"] for r in res["rows"]] == [6, 4]
    for r in res["rows"]:
        s = json.loads((tmp_path / "sw" / f"every{r['capture_every']}" / "summary.json").read_text())
        assert r["gain"] == pytest.approx(1 - s["arms"]["capture+synth"]["rms"] / s["arms"]["capture"]["rms"])
    assert res["crossover"]["kind"] in ("between", "helps_everywhere", "hurts_everywhere", "mixed")
    for f in ("sweep.md", "sweep.png", "sweep.json"):
        assert (tmp_path / "sw" / f).stat().st_size > 0
    assert res["crossover_text"] in (tmp_path / "sw" / "sweep.md").read_text().lower()


@pytest.mark.slow  # one tiny experiment through the CLI (~5 s unloaded)
def test_cli_quick_recipe_and_sweep_errors(saved_toy, tmp_path, capsys):
    good, _ = saved_toy
    out = tmp_path / "q"
    assert main(["sim2real", "depth", str(good), "--quick", "--capture-every", "2", "--synth", "4", "--steps", "2",
                 "--seeds", "0", "--width", "8", "--out", str(out), "--quiet"]) == 0
    cfg = json.loads((out / "summary.json").read_text())["config"]
    assert cfg["size_wh"] == [64, 48] and cfg["batch_real"] == 8  # --quick's values where not overridden
    assert (out / "rms_vs_distance.png").stat().st_size > 0
    capsys.readouterr()
    assert main(["sim2real", "depth", str(good), "--sweep-capture-every", "2,8", "--out", str(tmp_path / "s")]) == 1
    err = capsys.readouterr().err.strip()
    assert "leaves 1 capture frame" in err and "\n" not in err
    assert not (tmp_path / "s" / "every2").exists()  # checked before anything ran
