"""Report and figures of the sim2real depth experiment: ``report.md``, ``rms_vs_distance.png``,
``learning_curves.png``, ``examples.png``.

Nothing here decides a number of the experiment (it is outside ``code_version()``): it pools the
per-test-frame errors that each run file stores, so a finer binning of the test frames by their
distance to the capture is a matter of reporting, not of rerunning.

    curve = distance_curve(runs, test_dist, n_bins=10)     # RMS per arm over distance deciles
    overall_change(summary)                                 # capture+synth vs capture, per seed
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from presim.evaluation.sim2real.split import BINS
from presim.io_utils import atomic_write_bytes

__all__ = ["FINE_BINS", "MIN_FRAMES_PER_FINE_BIN", "distance_curve", "far_gap", "fine_bin_count",
           "overall_change", "report_markdown", "write_figures"]

ARMS = ("capture", "capture+synth", "synth")
FINE_BINS = 10
"""Number of equal-count distance bins of the finer binning (deciles of the test frames)."""
MIN_FRAMES_PER_FINE_BIN = 5
"""Fewer test frames than ``FINE_BINS`` x this: fewer fine bins (at least the three terciles)."""


def fine_bin_count(n_test: int) -> int:
    """Fine bins for ``n_test`` test frames: :data:`FINE_BINS`, fewer on small test sets."""
    return int(max(len(BINS), min(FINE_BINS, n_test // MIN_FRAMES_PER_FINE_BIN)))


def _mean_std(vals) -> tuple[float, float | None]:
    a = np.asarray(vals, np.float64)
    return float(a.mean()), (float(a.std(ddof=1)) if len(a) > 1 else None)


def distance_curve(runs: dict[str, list[dict]], dist: np.ndarray, n_bins: int | None = None) -> dict:
    """RMS per arm in ``n_bins`` equal-count bins of the test frames' distance to the capture.

    ``runs[arm]``: run results (one per seed) with ``per_frame.sq_sum`` / ``per_frame.n_pixels`` in
    test-frame order; ``dist``: (T,) combined distance of each test frame. Pixels of a bin are pooled
    per seed (as in the terciles), then mean and sample std over seeds. Returns ``{"bins": [{"d_min",
    "d_max", "d_median", "n_frames"}], "arms": {arm: {"rms": [...], "rms_std": [...], "seeds":
    {seed: [...]}}}}``."""
    dist = np.asarray(dist, np.float64)
    n_bins = fine_bin_count(len(dist)) if n_bins is None else int(n_bins)
    if not 1 <= n_bins <= len(dist):
        raise ValueError(f"n_bins must be in 1..{len(dist)} (the test frames), got {n_bins}")
    order = np.argsort(dist, kind="stable")
    chunks = np.array_split(order, n_bins)
    out = {"bins": [{"d_min": float(dist[c].min()), "d_max": float(dist[c].max()),
                     "d_median": float(np.median(dist[c])), "n_frames": int(len(c))} for c in chunks],
           "arms": {}}
    for arm, rs in runs.items():
        per_seed = {}
        for r in rs:
            sq = np.asarray(r["per_frame"]["sq_sum"], np.float64)
            n = np.asarray(r["per_frame"]["n_pixels"], np.float64)
            if len(sq) != len(dist):
                raise ValueError(f"{arm} seed {r['seed']}: {len(sq)} per-frame errors for {len(dist)} test frames")
            per_seed[str(r["seed"])] = [float(np.sqrt(sq[c].sum() / n[c].sum())) if n[c].sum() > 0 else float("nan")
                                        for c in chunks]
        vals = np.array(list(per_seed.values()))
        ms = [_mean_std(vals[:, j]) for j in range(n_bins)]
        out["arms"][arm] = {"rms": [m for m, _ in ms], "rms_std": [s for _, s in ms], "seeds": per_seed}
    return out


def far_gap(summary: dict) -> dict:
    """Far-bin RMS of capture+synth vs capture: relative change (negative = better) and seed spreads."""
    a, b = summary["arms"]["capture"]["bins"]["far"], summary["arms"]["capture+synth"]["bins"]["far"]
    return {"rms_capture": a["rms"], "rms_capture_synth": b["rms"], "rel_change": b["rms"] / a["rms"] - 1.0,
            "gap_m": a["rms"] - b["rms"], "std_capture": a["rms_std"], "std_capture_synth": b["rms_std"]}


def overall_change(summary: dict, arm: str = "capture+synth") -> dict:
    """Overall RMS of ``arm`` vs ``capture``: relative change of the seed means and of every seed
    (negative = better), and in how many seeds ``arm`` is better."""
    a, b = summary["arms"]["capture"], summary["arms"][arm]
    per = {s: b["seeds"][s]["overall"]["rms"] / a["seeds"][s]["overall"]["rms"] - 1.0 for s in a["seeds"]}
    return {"rel_change": b["rms"] / a["rms"] - 1.0, "per_seed": per,
            "seeds_better": int(sum(v < 0 for v in per.values())), "n_seeds": len(per),
            "worst_seed_change": max(per.values())}


def _pm(mean: float, std: float | None) -> str:
    return f"{mean:.3f}" if std is None else f"{mean:.3f} ± {std:.3f}"


def report_markdown(summary: dict, timing: dict) -> str:
    """``report.md``: the arms table, the per-seed change, the bins, the distance curve, timings."""
    c = summary["config"]
    lines = [f"# sim2real depth: {c['scene']}", "",
             f"Recipe `{c.get('recipe', 'custom')}`: capture every {c['capture_every']} -> {c['n_capture']} capture / "
             f"{c['n_test']} test frames; M = {c['synth']} synthesized views; {c['steps']} steps; seeds "
             f"{list(c['seeds'])}; size {c['size_wh'][0]}x{c['size_wh'][1]}; width {c['width']}; batch "
             f"{c['batch_real']} real + {c['batch_synth']} synth; device {c['device']}.",
             "", "| arm | RMS (m) | AbsRel | δ<1.25 | RMS near | RMS mid | RMS far |", "|---|---|---|---|---|---|---|"]
    for a, s in summary["arms"].items():
        cells = [_pm(s[k], s[f"{k}_std"]) for k in ("rms", "absrel", "delta1")]
        cells += [_pm(s["bins"][b]["rms"], s["bins"][b]["rms_std"]) for b in BINS]
        lines.append(f"| {a} | " + " | ".join(cells) + " |")
    ch = overall_change(summary)
    lines += ["", ("Values: mean ± sample std over seeds." if len(c["seeds"]) > 1 else "Values: one seed."), "",
              f"**capture+synth vs capture, overall RMS: {ch['rel_change'] * 100:+.1f} %** (per seed: "
              + ", ".join(f"seed {s} {v * 100:+.1f} %" for s, v in ch["per_seed"].items())
              + f"; better in {ch['seeds_better']} of {ch['n_seeds']} seeds)."]
    g = far_gap(summary)
    spread = ("one seed: no spread measured" if g["std_capture"] is None else
              f"seed std {g['std_capture_synth']:.3f} / {g['std_capture']:.3f} m")
    lines += [f"Far bin: capture+synth vs capture RMS {g['rel_change'] * 100:+.1f} % "
              f"({g['rms_capture_synth']:.3f} vs {g['rms_capture']:.3f} m; {spread}).",
              "", "| bin | frames | distance | median t (m) | median r (deg) |", "|---|---|---|---|---|"]
    for b in BINS:
        d = summary["bins"][b]
        lines.append(f"| {b} | {d['n_frames']} | {d['dist_min']:.2f}-{d['dist_max']:.2f} | "
                     f"{d['trans_m_median']:.3f} | {d['rot_deg_median']:.1f} |")
    curve = summary.get("distance_curve")
    if curve:
        lines += ["", f"RMS (m) against the distance to the capture, {len(curve['bins'])} equal-count bins "
                      "(distance d = t / 0.10 m + r / 10 deg; `rms_vs_distance.png`):", "",
                  "| d range | frames | " + " | ".join(curve["arms"]) + " | capture+synth vs capture |",
                  "|---|---|" + "---|" * len(curve["arms"]) + "---|"]
        for j, b in enumerate(curve["bins"]):
            cells = [_pm(v["rms"][j], v["rms_std"][j]) for v in curve["arms"].values()]
            a, s = curve["arms"]["capture"]["rms"][j], curve["arms"]["capture+synth"]["rms"][j]
            lines.append(f"| {b['d_min']:.2f}-{b['d_max']:.2f} | {b['n_frames']} | " + " | ".join(cells)
                         + f" | {(s / a - 1) * 100:+.1f} % |")
    lines += ["", f"Synthesizing {timing['synth_views']} views (+ capture-pose labels when rendered): "
                  f"{timing['synthesize_s']:.1f} s wall, {timing['synthesize_cpu_s']:.1f} s CPU; training per arm "
                  f"and seed (s wall): " + ", ".join(f"{a} {np.mean(v):.0f}" for a, v in timing["train_s"].items())
              + f"; this invocation {timing['this_invocation_s']:.0f} s wall, "
              f"{timing['this_invocation_cpu_s']:.0f} s CPU (load average at start "
              f"{timing['loadavg_start'][0]:.1f}, end {timing['loadavg_end'][0]:.1f}).", ""]
    return "\n".join(lines)


def _save_fig(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    atomic_write_bytes(path, buf.getvalue())


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_distance_figure(path: Path, summary: dict) -> None:
    """``rms_vs_distance.png``: left, RMS of each arm over the fine distance bins (mean ± std over
    seeds) with the terciles as horizontal segments over their distance range; right, the change of
    capture+synth and synth against capture per fine bin."""
    plt = _plt()
    curve = summary["distance_curve"]
    x = np.array([b["d_median"] for b in curve["bins"]])
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2))
    for k, (arm, v) in enumerate(curve["arms"].items()):
        col = f"C{k}"
        err = [0.0 if s is None else s for s in v["rms_std"]]
        ax[0].errorbar(x, v["rms"], yerr=err, fmt="o-", color=col, capsize=3, label=f"{arm} ({len(x)} bins)")
        tb = summary["arms"][arm]["bins"]
        for j, b in enumerate(BINS):
            d = summary["bins"][b]
            ax[0].hlines(tb[b]["rms"], d["dist_min"], d["dist_max"], colors=col, linestyles="--", lw=2.5,
                         alpha=0.6, label=f"{arm} terciles" if j == 0 else None)
        if arm != "capture":
            a = np.array(curve["arms"]["capture"]["rms"])
            ax[1].plot(x, (np.array(v["rms"]) / a - 1) * 100, "o-", color=col, label=f"{arm} vs capture")
    ax[0].set(xlabel="distance to the nearest capture frame, d = t/0.10 m + r/10°",
              ylabel="test RMS (m), mean ± std over seeds")
    ax[1].axhline(0, color="k", lw=0.8)
    ax[1].axhline(-10, color="grey", lw=0.8, ls=":")
    ax[1].set(xlabel=ax[0].get_xlabel(), ylabel="RMS change vs capture (%)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(f"{summary['config']['scene']}: capture every {summary['config']['capture_every']}", fontsize=10)
    fig.tight_layout()
    _save_fig(fig, path)
    plt.close(fig)


def write_figures(out: Path, summary: dict, runs: dict, examples: dict, test, steps: int, seeds, max_depth_m: float) -> None:
    """All figures of one experiment into ``out``."""
    plt = _plt()
    if summary.get("distance_curve"):
        write_distance_figure(out / "rms_vs_distance.png", summary)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    win = max(1, steps // 30)
    for arm, rs in runs.items():
        L = np.mean([r["train_loss"] for r in rs], axis=0)
        sm = np.convolve(L, np.ones(win) / win, mode="valid")
        ax[0].plot(np.arange(len(sm)) + win, sm, label=arm)
        pts = [p["step"] for p in rs[0]["test_curve"]]
        rms = np.mean([[p["rms"] for p in r["test_curve"]] for r in rs], axis=0)
        ax[1].plot(pts, rms, "o-", label=arm)
    ax[0].set(xlabel="step", ylabel="training loss (mean over seeds, smoothed)", yscale="log")
    ax[1].set(xlabel="step", ylabel="test RMS (m), all bins")
    for a in ax:
        a.legend()
        a.grid(alpha=0.3)
    fig.tight_layout()
    _save_fig(fig, out / "learning_curves.png")
    plt.close(fig)

    cols = ["image", "real depth"] + list(ARMS)
    fig, ax = plt.subplots(len(BINS), len(cols), figsize=(2.6 * len(cols), 2.2 * len(BINS)), squeeze=False)
    for r, row in enumerate(test.example_rows):
        gt = test.depth[row]
        vmax = float(gt[gt > 0].max()) if (gt > 0).any() else max_depth_m
        imgs = [test.rgb[row], np.ma.masked_where(gt <= 0, gt)] + [examples[a][r] for a in ARMS]
        for c, img in enumerate(imgs):
            a = ax[r, c]
            a.imshow(img) if c == 0 else a.imshow(img, cmap="turbo", vmin=0, vmax=vmax)
            a.set_xticks([])
            a.set_yticks([])
            if r == 0:
                a.set_title(cols[c] + ("" if c < 2 else f" (seed {seeds[0]})"), fontsize=9)
        ax[r, 0].set_ylabel(BINS[r])
    fig.tight_layout()
    _save_fig(fig, out / "examples.png")
    plt.close(fig)
