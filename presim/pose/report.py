"""Write an :class:`~presim.pose.evaluate.EvalReport`: tables (markdown, CSV, JSON) and plots (PNG).

Files in the output folder:

- ``summary.md``       per-object table like thesis Tables 6.1/6.2 + overall, BOP AR, notes, rejects
- ``per_object.csv``   the same table, machine-readable
- ``report.json``      everything (config, tables, curves, accuracy by visibility, rejections)
- ``per_target.csv``   one row per valid GT instance with the matched estimate's errors
- ``rejections.csv``   rejected result rows (line, reason)
- ``curve_add_s_cm.png``   accuracy vs ADD(-S) threshold 0-10 cm (Fig 6.5)
- ``curve_add_s_diam.png`` accuracy vs ADD(-S) threshold 0-100 % of the diameter
- ``curve_proj_px.png``    accuracy vs reprojection-error threshold (Fig 6.6)
- ``accuracy_vs_visibility.png`` accuracy (ADD(-S) < 2 cm and < 0.1 d) by visible fraction (Fig 6.13)
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from presim.io_utils import atomic_write_bytes, atomic_write_text
from presim.pose.evaluate import EvalReport, report_to_dict

__all__ = ["write_report", "summary_markdown", "COLUMNS"]

# (key, header, format) of the per-object table.
COLUMNS = [
    ("n_targets", "targets", "{:d}"),
    ("n_estimated", "estimated", "{:d}"),
    ("n_rejected_rows", "rejected rows", "{:d}"),
    ("auc_add", "ADD AUC", "{:.3f}"),
    ("auc_adi", "ADD-S AUC", "{:.3f}"),
    ("auc_add_s", "ADD(-S) AUC", "{:.3f}"),
    ("auc_add_s_diam", "ADD(-S) AUC 0-100%d", "{:.3f}"),
    ("acc_add_2cm", "ADD<2cm", "{:.3f}"),
    ("acc_adi_2cm", "ADD-S<2cm", "{:.3f}"),
    ("acc_add_s_2cm", "ADD(-S)<2cm", "{:.3f}"),
    ("acc_add_s_01d", "ADD(-S)<0.1d", "{:.3f}"),
    ("acc_add_s_01d_est", "ADD(-S)<0.1d (estimated only)", "{:.3f}"),
    ("mean_proj_px", "mean reproj px", "{:.2f}"),
    ("median_re_deg", "median re deg", "{:.2f}"),
    ("median_te_m", "median te cm", "cm"),
    ("ar_mssd", "AR_MSSD", "{:.3f}"),
    ("ar_mspd", "AR_MSPD", "{:.3f}"),
    ("ar_vsd", "AR_VSD", "{:.3f}"),
    ("ar", "AR", "{:.3f}"),
]


def _fmt(v, f: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if f == "cm":
        return f"{v * 100:.2f}"
    if f == "{:d}":
        return str(int(v))
    return f.format(v)


def _rows(rep: EvalReport):
    cols = [c for c in COLUMNS if any(c[0] in s for s in rep.per_object.values()) or c[0] in rep.overall]
    rows = []
    for obj_id, s in rep.per_object.items():
        name = f"{obj_id}{' (sym)' if s.get('symmetric') else ''}"
        rows.append((name, s))
    rows.append(("MEAN (objects)", rep.mean_over_objects))
    rows.append(("ALL (targets)", rep.overall))
    return cols, rows


def summary_markdown(rep: EvalReport) -> str:
    cols, rows = _rows(rep)
    lines = [f"# Pose evaluation", "", f"- dataset: `{rep.dataset}`", f"- results: `{rep.results}`",
             f"- ADD(-S) AUC: VOC-style (YCB_Video_toolbox) over 0-{rep.config.auc_max_m * 100:.0f} cm; "
             f"accuracy thresholds {rep.config.acc_threshold_m * 100:.0f} cm and {rep.config.acc_threshold_diam:g} d; "
             "missing estimates count as failures", ""]
    lines.append("| object | " + " | ".join(c[1] for c in cols) + " |")
    lines.append("|---" * (len(cols) + 1) + "|")
    for name, s in rows:
        lines.append(f"| {name} | " + " | ".join(_fmt(s.get(c[0]), c[2]) if c[0] in s else "" for c in cols) + " |")
    lines += ["", "## Accuracy by visible fraction (ADD(-S) < 2 cm / < 0.1 d)", "",
              "| visib_fract | n | ADD(-S)<2cm | ADD(-S)<0.1d |", "|---|---|---|---|"]
    e = rep.visibility["bin_edges"]
    for b in range(len(e) - 1):
        lines.append(f"| {e[b]:.1f}-{e[b + 1]:.1f} | {rep.visibility['n'][b]} | "
                     f"{_fmt(rep.visibility['acc_add_s_2cm'][b], '{:.3f}')} | {_fmt(rep.visibility['acc_add_s_01d'][b], '{:.3f}')} |")
    lines += ["", f"Rejected result rows: {len(rep.rejections)}"]
    for r in rep.rejections[:20]:
        lines.append(f"- line {r['line']}: {r['reason']}")
    if len(rep.rejections) > 20:
        lines.append(f"- ... {len(rep.rejections) - 20} more in rejections.csv")
    if rep.notes:
        lines += ["", "Notes:"] + [f"- {n}" for n in rep.notes]
    return "\n".join(lines) + "\n"


def _csv(header: list[str], rows: list[list]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def _plot_curves(rep: EvalReport, key: str, xscale: float, xlabel: str, title: str) -> bytes:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = rep.curves[key]
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    x = [v * xscale for v in c["thresholds"]]
    for label, ys in c.items():
        if label == "thresholds":
            continue
        ax.plot(x, ys, label="all" if label == "all" else f"obj {label}",
                lw=2.5 if label == "all" else 1.2, color="k" if label == "all" else None)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("accuracy")
    ax.set_ylim(0, 1)
    ax.set_xlim(x[0], x[-1])
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=2)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _plot_visibility(rep: EvalReport) -> bytes:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = rep.visibility
    e = v["bin_edges"]
    centres = [(e[i] + e[i + 1]) / 2 for i in range(len(e) - 1)]
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    for key, label in (("acc_add_s_2cm", "ADD(-S) < 2 cm"), ("acc_add_s_01d", "ADD(-S) < 0.1 d")):
        pts = [(c, a) for c, a in zip(centres, v[key]) if a is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=label)
    ax2 = ax.twinx()
    ax2.bar(centres, v["n"], width=(e[1] - e[0]) * 0.8, alpha=0.15, color="gray")
    ax2.set_ylabel("instances")
    ax.set_xlabel("visible fraction of the object")
    ax.set_ylabel("accuracy")
    ax.set_ylim(0, 1)
    ax.set_zorder(ax2.get_zorder() + 1)
    ax.patch.set_visible(False)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Accuracy vs visible fraction")
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def write_report(rep: EvalReport, out_dir: str | Path) -> Path:
    """Write all report files into ``out_dir`` (created; each file written atomically)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "summary.md", summary_markdown(rep))
    cols, rows = _rows(rep)
    atomic_write_text(out / "per_object.csv", _csv(
        ["object"] + [c[0] for c in cols],
        [[name] + ["" if s.get(c[0]) is None else s.get(c[0]) for c in cols] for name, s in rows]))
    atomic_write_text(out / "report.json", json.dumps(report_to_dict(rep), indent=1) + "\n")
    fields = ["scene_id", "im_id", "obj_id", "gt_idx", "visib_fract", "est_line", "score", "add", "adi", "add_s",
              "add_s_diam", "proj", "re_deg", "te", "mssd", "mspd"]
    atomic_write_text(out / "per_target.csv", _csv(fields, [[getattr(r, f) for f in fields] for r in rep.records]))
    atomic_write_text(out / "rejections.csv", _csv(["line", "reason", "obj_id", "text"],
                                                   [[r["line"], r["reason"], r["obj_id"], r["text"]] for r in rep.rejections]))
    atomic_write_bytes(out / "curve_add_s_cm.png", _plot_curves(rep, "add_s_m", 100.0, "ADD(-S) threshold [cm]",
                                                                "Accuracy vs ADD(-S) threshold"))
    atomic_write_bytes(out / "curve_add_s_diam.png", _plot_curves(rep, "add_s_diam", 100.0, "ADD(-S) threshold [% of diameter]",
                                                                  "Accuracy vs ADD(-S) / diameter"))
    atomic_write_bytes(out / "curve_proj_px.png", _plot_curves(rep, "proj_px", 1.0, "reprojection error threshold [px]",
                                                               "Accuracy vs reprojection error"))
    atomic_write_bytes(out / "accuracy_vs_visibility.png", _plot_visibility(rep))
    return out
