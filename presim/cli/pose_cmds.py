"""``presim pose-eval``: score 6D pose estimates (BOP results CSV) against a BOP dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "pose-eval",
        help="score 6D pose estimates (BOP CSV) on a BOP dataset: ADD(-S), AUC, reprojection, BOP AR",
        description="Score BOP'19 results (scene_id,im_id,obj_id,score,R,t,time) against a BOP dataset. "
                    "Writes per-object tables (markdown, CSV, JSON), accuracy curves and accuracy by "
                    "visible fraction into --out.",
    )
    p.add_argument("--dataset", required=True, type=Path, help="BOP dataset root (models/, <split>/)")
    p.add_argument("--results", required=True, type=Path, help="BOP results CSV")
    p.add_argument("--targets", type=Path, default=None,
                   help="targets JSON (default: <dataset>/test_targets_bop19.json, else all >=10%% visible)")
    p.add_argument("--scene-ids", type=int, nargs="+", default=None, help="evaluate only these scenes")
    p.add_argument("--symmetric", type=int, nargs="+", default=(), metavar="OBJ_ID",
                   help="object ids scored with ADD-S (besides models_info symmetries), e.g. LM-O: 10 11")
    p.add_argument("--split", default="test", help="split folder (default test)")
    p.add_argument("--vsd", choices=("auto", "on", "off"), default="auto",
                   help="VSD/AR_VSD: auto = when every target image has depth")
    p.add_argument("--device", default="cpu", help="cpu | cuda (torch)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from presim.pose.evaluate import EvalConfig, evaluate_files
    from presim.pose.report import write_report

    cfg = EvalConfig(split=args.split, targets_path=args.targets,
                     scene_ids=tuple(args.scene_ids) if args.scene_ids else None,
                     symmetric_obj_ids=tuple(args.symmetric), vsd=args.vsd, device=args.device)
    rep = evaluate_files(args.dataset, args.results, cfg)
    out = write_report(rep, args.out)
    o = rep.overall
    print(f"targets {o['n_targets']}  estimated {o['n_estimated']}  rejected rows {o['n_rejected_rows']}")
    print(f"ADD(-S) AUC {o['auc_add_s']:.3f}  ADD(-S)<2cm {o['acc_add_s_2cm']:.3f}  "
          f"ADD(-S)<0.1d {o['acc_add_s_01d']:.3f}  mean reproj {o['mean_proj_px']:.2f} px")
    ar = "  ".join(f"{k.upper()} {o[k]:.3f}" for k in ("ar_vsd", "ar_mssd", "ar_mspd", "ar") if k in o)
    if ar:
        print(ar)
    for n in rep.notes:
        print(f"note: {n}", file=sys.stderr)
    print(f"report: {out / 'summary.md'}")
    return 0
