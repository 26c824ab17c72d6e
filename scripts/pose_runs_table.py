"""Mean ± sample std over seeds of `presim pose-eval` reports, as the markdown tables of
docs/pose-networks.md.

    python scripts/pose_runs_table.py "DenseFusion=out/pn/densefusion_s?_eval" "C/G-AF=out/pn/cgaf_s?_eval"

Each argument is LABEL=GLOB; GLOB matches pose-eval output folders (each with report.json), one per
seed. Prints one overall table (ADD(-S) AUC, < 2 cm, < 0.1 d) and one per-object ADD(-S) AUC table.
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    args = ap.parse_args(argv)
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
        rows.append((label, [p.parent.name for p in paths], aggregate([json.loads(p.read_text()) for p in paths])))
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
    for label, names, _ in rows:
        print(f"\n{label}: {', '.join(names)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
