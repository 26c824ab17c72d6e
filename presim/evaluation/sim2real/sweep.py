"""Capture-density sweep of the sim2real depth experiment: the same recipe at several ``capture_every``
values, and where synthesized views stop helping.

    run_capture_sweep(scene, cfg, (10, 25, 50), out_dir)   # DIR/every10/, every25/, every50/ + sweep.*

Each density is one ordinary experiment in ``DIR/every<N>/`` (resumable on its own). The gain at a
density is ``(RMS_capture - RMS_capture+synth) / RMS_capture`` of the overall test RMS (positive =
synthesized views help). The crossover is the ``capture_every`` where the gain, linearly interpolated
between neighbouring densities, crosses zero going from dense (small N) to sparse (large N).
"""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np

from presim.capture.scene import Scene
from presim.evaluation.sim2real.experiment import DepthExperimentConfig, run_depth_experiment
from presim.evaluation.sim2real.report import overall_change
from presim.evaluation.sim2real.split import split_capture
from presim.io_utils import atomic_write_bytes, atomic_write_json, atomic_write_text

__all__ = ["crossover", "parse_capture_every_list", "run_capture_sweep"]


def parse_capture_every_list(text: str) -> tuple[int, ...]:
    """``"10,25,50"`` -> (10, 25, 50): at least two distinct integers >= 2, sorted."""
    try:
        vals = sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise ValueError(f"--sweep-capture-every must be comma-separated integers, e.g. 10,25,50, got {text!r}") from None
    if len(vals) < 2 or vals[0] < 2:
        raise ValueError(f"--sweep-capture-every needs at least two distinct values >= 2, got {text!r}")
    return tuple(vals)


def crossover(capture_every: list[int], gain: list[float]) -> dict:
    """Where the gain crosses zero, densest first.

    Returns ``{"kind": "between", "capture_every": x}`` (the gain is <= 0 up to some density and > 0
    from the next one on; x = linear interpolation of the zero between those two),
    ``"helps_everywhere"`` (gain > 0 at every density: the crossover is denser than the densest one
    measured), ``"hurts_everywhere"`` (no density with a gain), or ``"mixed"`` (any other pattern;
    x = the first zero crossing)."""
    order = np.argsort(capture_every)
    n = [int(capture_every[i]) for i in order]
    g = [float(gain[i]) for i in order]
    if all(v > 0 for v in g):
        return {"kind": "helps_everywhere", "capture_every": None, "densest": n[0]}
    if all(v <= 0 for v in g):
        return {"kind": "hurts_everywhere", "capture_every": None, "sparsest": n[-1]}
    first = next((k for k in range(1, len(g)) if g[k - 1] <= 0 < g[k]), None)
    if first is None:  # helps when dense, hurts when sparse: take the first sign change
        first = next(k for k in range(1, len(g)) if (g[k - 1] > 0) != (g[k] > 0))
    x = n[first - 1] + (n[first] - n[first - 1]) * (0 - g[first - 1]) / (g[first] - g[first - 1])
    kind = "between" if all(v > 0 for v in g[first:]) and all(v <= 0 for v in g[:first]) else "mixed"
    return {"kind": kind, "capture_every": float(x), "between": [n[first - 1], n[first]]}


def _crossover_text(c: dict) -> str:
    if c["kind"] == "helps_everywhere":
        return (f"synthesized views help at every density measured; the crossover is at a denser capture "
                f"than every {c['densest']} frames")
    if c["kind"] == "hurts_everywhere":
        return f"synthesized views help at no density measured (sparsest: every {c['sparsest']} frames)"
    s = (f"crossover at a capture of about every {c['capture_every']:.1f} frames (the gain crosses zero between "
         f"every {c['between'][0]} and every {c['between'][1]}; linear interpolation)")
    return s if c["kind"] == "between" else s + "; the gain changes sign more than once"


def run_capture_sweep(scene: Scene, cfg: DepthExperimentConfig, capture_every: tuple[int, ...],
                      out_dir: str | Path, scene_label: str = "", restart: bool = False) -> dict:
    """Run ``cfg`` at every density in ``capture_every`` into ``out_dir/every<N>``, then write
    ``sweep.json``, ``sweep.md`` and ``sweep.png`` (gain against density). Every density is checked
    (enough capture and test frames) before anything runs."""
    out = Path(out_dir)
    for n in capture_every:
        split_capture(scene.T_world_cam, n)  # one-line error before hours of training
    rows = []
    for n in capture_every:
        s = run_depth_experiment(scene, replace(cfg, capture_every=n), out / f"every{n}", scene_label, restart)
        ch = overall_change(s)
        bins = s["bins"]
        rows.append({"capture_every": n, "n_capture": s["config"]["n_capture"], "n_test": s["config"]["n_test"],
                     "rms": {a: s["arms"][a]["rms"] for a in s["arms"]},
                     "rms_std": {a: s["arms"][a]["rms_std"] for a in s["arms"]},
                     "gain": -ch["rel_change"], "gain_per_seed": {k: -v for k, v in ch["per_seed"].items()},
                     "seeds_better": ch["seeds_better"], "n_seeds": ch["n_seeds"],
                     "far_gain": 1.0 - s["arms"]["capture+synth"]["bins"]["far"]["rms"]
                     / s["arms"]["capture"]["bins"]["far"]["rms"],
                     "median_trans_m": {b: bins[b]["trans_m_median"] for b in ("near", "mid", "far")},
                     "median_rot_deg": {b: bins[b]["rot_deg_median"] for b in ("near", "mid", "far")}})
    cross = crossover([r["capture_every"] for r in rows], [r["gain"] for r in rows])
    sweep = {"rows": rows, "crossover": cross, "crossover_text": _crossover_text(cross),
             "scene": scene_label or str(scene.path or scene.meta.source), "seeds": list(cfg.seeds)}
    _write_plot(out / "sweep.png", sweep)
    atomic_write_text(out / "sweep.md", _markdown(sweep))
    atomic_write_json(out / "sweep.json", sweep)
    return sweep


def _markdown(sweep: dict) -> str:
    lines = [f"# sim2real depth: capture-density sweep, {sweep['scene']}", "",
             "| capture every | capture / test frames | RMS capture | RMS capture+synth | RMS synth | gain | "
             "gain per seed | far-bin gain | median t, r of the mid bin |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sweep["rows"]:
        rms = [f"{r['rms'][a]:.3f}" for a in ("capture", "capture+synth", "synth")]
        per = ", ".join(f"{v * 100:+.1f}" for v in r["gain_per_seed"].values())
        lines.append(f"| {r['capture_every']} | {r['n_capture']} / {r['n_test']} | " + " | ".join(rms)
                     + f" | {r['gain'] * 100:+.1f} % | {per} | {r['far_gain'] * 100:+.1f} % | "
                     f"{r['median_trans_m']['mid'] * 100:.1f} cm, {r['median_rot_deg']['mid']:.1f}° |")
    lines += ["", "Gain = (RMS capture − RMS capture+synth) / RMS capture, overall test RMS (positive: the "
              "synthesized views help).", f"**{sweep['crossover_text'][0].upper() + sweep['crossover_text'][1:]}.**", ""]
    return "\n".join(lines)


def _write_plot(path: Path, sweep: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["capture_every"] for r in sweep["rows"]]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.plot(n, [r["gain"] * 100 for r in sweep["rows"]], "o-", label="overall, mean over seeds")
    for s in sweep["rows"][0]["gain_per_seed"]:
        ax.plot(n, [r["gain_per_seed"][s] * 100 for r in sweep["rows"]], ".", alpha=0.5, color="C0")
    ax.plot(n, [r["far_gain"] * 100 for r in sweep["rows"]], "s--", label="far bin")
    ax.axhline(0, color="k", lw=0.8)
    c = sweep["crossover"]
    if c["capture_every"] is not None:
        ax.axvline(c["capture_every"], color="grey", ls=":", label=f"crossover ≈ every {c['capture_every']:.1f}")
    ax.set(xlabel="capture every N-th frame (sparser →)", ylabel="RMS gain of capture+synth vs capture (%)",
           title=f"{sweep['scene']}", xticks=n)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    atomic_write_bytes(path, buf.getvalue())
    plt.close(fig)
