"""Mean ± sample std over seeds of `presim pose-eval` reports, as the markdown tables of
docs/pose-networks.md.

    python scripts/pose_runs_table.py "DenseFusion=out/pn/densefusion_s?_eval" "C/G-AF=out/pn/cgaf_s?_eval"

Each argument is LABEL=GLOB; GLOB matches pose-eval output folders (each with report.json), one per
seed. Prints one overall table (ADD(-S) AUC, < 2 cm, < 0.1 d) and one per-object ADD(-S) AUC table;
with ``--visibility`` also ADD(-S) < 0.1 d per visible-fraction bin (Fig. 6.13 style), and with
``--plot OUT.png`` that curve as a figure.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

OVERALL = (("auc_add_s", "ADD(-S) AUC"), ("acc_add_s_2cm", "< 2 cm"), ("acc_add_s_01d", "< 0.1 d"))


def mean_std(values: list[float]) -> str:
    """``"m ± s"`` (sample std, ddof = 1); a single value has no spread and is printed alone."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 1:
        return f"{v[0]:.3f}"
    return f"{v.mean():.3f} ± {v.std(ddof=1):.3f}"


def aggregate(reports: list[dict]) -> dict:
    """``{"n": runs, "overall": {metric: [per run]}, "per_object": {obj: [auc per run]}}``."""
    out = {"n": len(reports), "overall": {k: [] for k, _ in OVERALL}, "per_object": {}}
    for r in reports:
        for k, _ in OVERALL:
            out["overall"][k].append(float(r["overall"][k]))
        for obj, m in r["per_object"].items():
            label = f"{obj} (sym)" if m.get("symmetric") else obj
            out["per_object"].setdefault(label, []).append(float(m["auc_add_s"]))
    return out


def visibility_curve(reports: list[dict], metric: str = "acc_add_s_01d") -> tuple[list[float], list[int], list]:
    """Bin edges, targets per bin and the mean over runs of ``metric`` per bin (None where empty)."""
    edges = reports[0]["visibility"]["bin_edges"]
    n = reports[0]["visibility"]["n"]
    vals = []
    for b in range(len(n)):
        xs = [r["visibility"][metric][b] for r in reports if r["visibility"][metric][b] is not None]
        vals.append(float(np.mean(xs)) if xs else None)
    return edges, n, vals


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    ap.add_argument("--visibility", action="store_true", help="also ADD(-S) < 0.1 d per visible-fraction bin")
    ap.add_argument("--plot", type=Path, help="write the visibility curve as a PNG here")
    args = ap.parse_args(argv)
    reports_by_label = {}
    rows = []
    for g in args.groups:
        if "=" not in g:
            print(f"error: {g!r}: expected LABEL=GLOB", file=sys.stderr)
            return 2
        label, pattern = g.split("=", 1)
        dirs = sorted(glob.glob(pattern))
        paths = [Path(d) / "report.json" for d in dirs if (Path(d) / "report.json").is_file()]
        if not paths:
            print(f"error: {pattern}: no pose-eval folder with report.json", file=sys.stderr)
            return 2
        reports = [json.loads(p.read_text()) for p in paths]
        reports_by_label[label] = reports
        rows.append((label, [p.parent.name for p in paths], aggregate(reports)))
    print("| model | runs | " + " | ".join(n for _, n in OVERALL) + " |")
    print("|---|---|" + "---|" * len(OVERALL))
    for label, names, a in rows:
        print(f"| {label} | {a['n']} | " + " | ".join(mean_std(a["overall"][k]) for k, _ in OVERALL) + " |")
    objs = sorted({o for _, _, a in rows for o in a["per_object"]}, key=lambda s: int(s.split()[0]))
    print("\n| model (ADD(-S) AUC per object) | " + " | ".join(objs) + " |")
    print("|---|" + "---|" * len(objs))
    for label, _, a in rows:
        print(f"| {label} | " + " | ".join(mean_std(a["per_object"][o]) if o in a["per_object"] else "—"
                                          for o in objs) + " |")
    if args.visibility or args.plot:
        curves = {label: visibility_curve(r) for label, r in reports_by_label.items()}
        edges, n, _ = next(iter(curves.values()))
        bins = [b for b in range(len(n)) if n[b]]
        print("\n| ADD(-S) < 0.1 d, visible fraction | " + " | ".join(f"{edges[b]:.1f}-{edges[b + 1]:.1f}" for b in bins)
              + " |")
        print("|---|" + "---|" * len(bins))
        print("| targets | " + " | ".join(str(n[b]) for b in bins) + " |")
        for label, (_, _, vals) in curves.items():
            print(f"| {label} | " + " | ".join(f"{vals[b]:.3f}" for b in bins) + " |")
        if args.plot:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(6, 3.6))
            centres = [(edges[b] + edges[b + 1]) / 2 for b in bins]
            for label, (_, _, vals) in curves.items():
                ax.plot(centres, [vals[b] for b in bins], marker="o", label=f"{label} (mean of {len(reports_by_label[label])})")
            for c, b in zip(centres, bins):
                ax.annotate(f"n={n[b]}", (c, 0.02), ha="center", fontsize=7, color="grey")
            ax.set_xlabel("visible fraction of the object")
            ax.set_ylabel("ADD(-S) < 0.1 d")
            ax.set_ylim(0, 1)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
            fig.tight_layout()
            tmp = args.plot.with_suffix(".tmp.png")
            fig.savefig(tmp, dpi=110)
            tmp.replace(args.plot)
    for label, names, _ in rows:
        print(f"\n{label}: {', '.join(names)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
