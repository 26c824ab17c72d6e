"""``presim sim2real depth``: monocular depth trained on the capture vs on synthesized views, tested
on real frames away from the capture (thesis §4.5, Table 4.3; docs/sim2real.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["register"]


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must be WxH, e.g. 64x48, got {text!r}") from None
    return w, h


def register(sub) -> None:
    p = sub.add_parser("sim2real", help="evidence that synthesized views transfer to real images",
                       description="Sim-to-real experiments (thesis §4.5). See docs/sim2real.md.")
    tasks = p.add_subparsers(dest="sim2real_task", metavar="TASK", title="tasks")
    from presim.cli import HelpFormatter

    d = tasks.add_parser(
        "depth", formatter_class=HelpFormatter,
        help="monocular depth: capture vs capture+synth vs synth, tested on real held-out frames",
        description="Train a small DenseDepth-style network three ways (capture frames only; the same real "
                    "batches plus synthesized views; synthesized views only) and test each on the scene's "
                    "other real frames, binned by distance to the capture. Resumes per arm and seed.")
    d.add_argument("scene", type=Path, help="saved scene folder (presim import / presim sample-scene)")
    density = d.add_mutually_exclusive_group(required=True)
    density.add_argument("--capture-every", type=int, metavar="N",
                         help="capture = frames 0, N, 2N, ...; all other frames are real test frames")
    density.add_argument("--sweep-capture-every", metavar="N1,N2,...",
                         help="run the experiment at each capture density (DIR/every<N>/) and plot the gain of "
                              "capture+synth over capture against the density (DIR/sweep.md, sweep.png)")
    d.add_argument("--out", type=Path, required=True, help="output folder (created; rerun to resume)")
    d.add_argument("--quick", action="store_true",
                   help="the small recipe for tests and demos: 64x48, 1000 steps, --synth 400 (about a quarter "
                        "of the CPU time per step; smaller gain); flags below override either recipe")
    d.add_argument("--synth", type=int, metavar="M",
                   help="number of synthesized training views (default: 1000; --quick: 400)")
    d.add_argument("--steps", type=int, help="optimiser steps per arm and seed (default: 1200; --quick: 1000)")
    d.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds")
    d.add_argument("--size", type=_size, metavar="WxH", help="model input size (default: 160x120; --quick: 64x48)")
    d.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                   help="torch device of the training (rendering stays on the CPU); cpu is the tested path")
    d.add_argument("--width", type=int, help="encoder channel width (default: 16; 64 = ResNet-18's)")
    d.add_argument("--batch-real", type=int, help="real capture frames per step (default: 8)")
    d.add_argument("--batch-synth", type=int, help="synthesized views per step (default: 8)")
    d.add_argument("--lr", type=float, default=1e-3, help="Adam peak learning rate")
    d.add_argument("--schedule", default="cosine", choices=("cosine", "constant"),
                   help="learning-rate schedule: cosine = 5%% linear warm-up, then cosine decay to 1%% of --lr")
    d.add_argument("--real-labels", default="rendered", choices=("rendered", "sensor"),
                   help="capture-frame labels: the renderer's depth at the capture pose (same density as the "
                        "synthesized labels) or the sensor depth resized; test labels are always sensor depth")
    d.add_argument("--scene-poses", choices=("given", "refined", "auto"), default="given",
                   help="camera poses: the capture's given ones (default; `presim align` refines with every "
                        "frame, test frames included), refined (error when absent) or auto")
    d.add_argument("--restart", action="store_true",
                   help="delete results in --out made with another configuration or code version and start "
                        "over (without it such a folder is refused)")
    d.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    d.add_argument("--pose-seed", type=int, default=0, help="seed of the synthesized poses")
    d.add_argument("--refine", action="store_true",
                   help="refine the capture frames' depth from capture frames only and train/render from it "
                        "(slow on CPU; test labels stay sensor depth)")
    d.set_defaults(func=_depth)


def _depth(args: argparse.Namespace) -> int:
    from presim.capture.store import is_scene_dir, load_scene
    from presim.evaluation.sim2real.experiment import recipe_config, run_depth_experiment
    from presim.evaluation.sim2real.report import far_gap, overall_change
    from presim.evaluation.sim2real.sweep import parse_capture_every_list, run_capture_sweep

    if not args.scene.exists():
        raise FileNotFoundError(f"{args.scene}: scene folder not found")
    if not is_scene_dir(args.scene):
        raise FileNotFoundError(f"{args.scene}: not a saved scene (no scene.json); import it with `presim import`")
    from presim.limits import check_memory, check_positive, check_positive_int

    for flag in ("steps", "width", "batch_real", "batch_synth", "capture_every"):
        check_positive_int(getattr(args, flag), "--" + flag.replace("_", "-"), allow_none=True)
    check_positive_int(args.threads, "--threads", allow_none=False)
    check_positive(args.lr, "--lr", allow_none=False)
    sweep = parse_capture_every_list(args.sweep_capture_every) if args.sweep_capture_every else None
    cfg = recipe_config("quick" if args.quick else "default",
                        capture_every=args.capture_every if sweep is None else sweep[0],
                        synth=args.synth, steps=args.steps, size_wh=None if args.size is None else tuple(args.size),
                        width=args.width, batch_real=args.batch_real, batch_synth=args.batch_synth,
                        seeds=tuple(dict.fromkeys(args.seeds)), lr=args.lr, device=args.device,
                        threads=args.threads, pose_seed=args.pose_seed, refine=args.refine,
                        schedule=args.schedule, real_labels=args.real_labels)
    w, h = cfg.size_wh
    if w > 1280 or h > 960:
        raise ValueError(f"--size {w}x{h}: at most 1280x960 (the model runs at a reduced size)")
    scene = load_scene(args.scene, poses=args.scene_poses)
    # Model-size frames and views (uint8 RGB + float32 depth, with left-right flips in the training
    # pool: ~2x) plus training activations (~40 floats per pixel per channel of width, forward +
    # backward). Full-size frames are streamed, not held.
    frames = len(scene) + cfg.synth
    est = 2 * frames * w * h * 7 + (cfg.batch_real + cfg.batch_synth) * w * h * cfg.width * 160
    check_memory(est, "--size/--synth", f"sim2real depth at {w}x{h} with {cfg.synth} views", args.max_memory)
    if sweep is not None:
        res = run_capture_sweep(scene, cfg, sweep, args.out, scene_label=str(args.scene), restart=args.restart)
        for r in res["rows"]:
            print(f"every {r['capture_every']:3d}: capture {r['rms']['capture']:.3f}  capture+synth "
                  f"{r['rms']['capture+synth']:.3f}  synth {r['rms']['synth']:.3f} m  gain {r['gain'] * 100:+.1f} %")
        print(res["crossover_text"])
        print(f"wrote {args.out}/sweep.md, sweep.png, sweep.json and every<N>/")
        return 0
    summary = run_depth_experiment(scene, cfg, args.out, scene_label=str(args.scene), restart=args.restart)
    for arm, s in summary["arms"].items():
        sd = "" if s["rms_std"] is None else f" ± {s['rms_std']:.3f}"
        print(f"{arm:14s} RMS {s['rms']:.3f}{sd} m  AbsRel {s['absrel']:.3f}  "
              f"δ1 {s['delta1']:.3f}  far RMS {s['bins']['far']['rms']:.3f} m")
    print(json.dumps({"overall": overall_change(summary), "far_bin": far_gap(summary)}))
    print(f"wrote {args.out}/summary.json, report.md, rms_vs_distance.png, learning_curves.png, examples.png")
    return 0
