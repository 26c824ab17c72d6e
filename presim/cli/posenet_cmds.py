"""``presim pose-train`` / ``presim pose-predict``: train the pose networks on a BOP folder, write BOP CSV estimates."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

_MODELS = ("densefusion", "cgaf", "cgaf-noatt", "segmentation")


def register(sub) -> None:
    p = sub.add_parser(
        "pose-train",
        help="train a 6D pose network (DenseFusion, C/G-AF) or the segmentation network on a BOP folder",
        description="Train on the instances of a BOP split with depth. Writes config.json, checkpoint_last.pt, "
                    "metrics.csv and learning_curve.png into --out; rerunning on the same --out resumes "
                    "(docs/pose-networks.md). Without --epochs: the CPU quick recipe.",
    )
    p.add_argument("--dataset", required=True, type=Path, help="BOP dataset root (models/, <split>/)")
    p.add_argument("--model", required=True, choices=_MODELS, help="network to train")
    p.add_argument("--out", required=True, type=Path, help="run folder (created; resumed when it holds a run)")
    p.add_argument("--split", default="train", help="split folder (default train)")
    p.add_argument("--epochs", type=int, default=None,
                   help="epochs (default: the quick recipe, a fixed number of optimiser steps, see --steps)")
    p.add_argument("--steps", type=int, default=None,
                   help="optimiser steps when --epochs is not given (default: the quick recipe's)")
    p.add_argument("--refine-steps", type=int, default=None,
                   help="last steps that train the refiner alone on the frozen estimator (default 0: no refiner)")
    p.add_argument("--batch-size", type=int, default=None, help="instances (images for segmentation) per step")
    p.add_argument("--lr", type=float, default=None,
                   help="peak Adam learning rate (default: the quick recipe's, 1e-3; segmentation 3e-3)")
    p.add_argument("--points", type=int, default=None, help="depth points per instance")
    p.add_argument("--max-instances", type=int, default=0, help="train on at most this many instances (0 = all)")
    p.add_argument("--full-size", action="store_true", help="published network sizes (GPU recipe)")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.set_defaults(func=_train)

    q = sub.add_parser(
        "pose-predict",
        help="6D pose estimates of a trained run on a BOP split, as a BOP CSV for pose-eval",
        description="Run a pose-train run on every >=10%%-visible instance of a BOP split (ground-truth "
                    "masks, or those of a segmentation run) and write scene_id,im_id,obj_id,score,R,t,time.",
    )
    q.add_argument("--dataset", required=True, type=Path, help="BOP dataset root")
    q.add_argument("--checkpoint", required=True, type=Path, help="pose-train run folder of a pose model")
    q.add_argument("--segmentation", type=Path, default=None, help="pose-train run folder of a segmentation model")
    q.add_argument("--split", default="test", help="split folder (default test)")
    q.add_argument("--refine-iters", type=int, default=-1, help="refinement iterations (default: the run's)")
    q.add_argument("--device", default="cpu", help="cpu | cuda")
    q.add_argument("--out", required=True, type=Path, help="results CSV to write")
    q.set_defaults(func=_predict)


def _require_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise ImportError("the pose networks need PyTorch (`pip install -e .[torch]`)") from None


def _train(args: argparse.Namespace) -> int:
    _require_torch()
    from dataclasses import replace

    from presim.limits import check_positive
    from presim.pose.nets.train import TrainConfig, train

    cfg = TrainConfig(model=args.model, device=args.device, seed=args.seed, full_size=args.full_size,
                      max_instances=args.max_instances)
    cfg = replace(cfg, data=replace(cfg.data, split=args.split, seed=args.seed))
    if args.epochs is not None:
        if args.epochs < 1:
            raise ValueError(f"--epochs: must be >= 1, got {args.epochs}")
        cfg = replace(cfg, epochs=args.epochs)
    if args.steps is not None:
        if args.steps < 1:
            raise ValueError(f"--steps: must be >= 1, got {args.steps}")
        cfg = replace(cfg, steps=args.steps)
    if args.refine_steps is not None:
        if args.refine_steps < 0:
            raise ValueError(f"--refine-steps: must be >= 0, got {args.refine_steps}")
        cfg = replace(cfg, refine_steps=args.refine_steps)
    if args.batch_size is not None:
        cfg = replace(cfg, batch_size=args.batch_size)
    if args.lr is not None:
        check_positive(args.lr, "--lr", allow_none=False)
        cfg = replace(cfg, lr=args.lr)
    if args.points is not None:
        cfg = replace(cfg, data=replace(cfg.data, n_points=args.points))
    rep = train(args.dataset, args.out, cfg)
    if rep.resumed_from and rep.resumed_from >= len(rep.rows):
        print(f"{args.out}: already trained for {rep.resumed_from} epochs (raise --epochs or --steps to continue)")
    last = rep.rows[-1] if rep.rows else {}
    print(" ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in last.items()))
    print(f"run: {args.out} (metrics.csv, learning_curve.png, checkpoint_last.pt)")
    return 0


def _predict(args: argparse.Namespace) -> int:
    _require_torch()
    from presim.pose.nets.predict import PredictConfig, predict
    from presim.pose.results import write_bop_results

    est = predict(args.dataset, args.checkpoint,
                  PredictConfig(split=args.split, device=args.device, refine_iters=args.refine_iters),
                  segmentation=args.segmentation)
    write_bop_results(args.out, est)
    if args.segmentation is not None:
        from presim.pose.nets.segmentation import segmentation_iou
        iou = segmentation_iou(args.dataset, args.segmentation, args.split, args.device)
        print("segmentation IoU per object: " + "  ".join(f"{o}: {v:.3f}" for o, v in iou.items())
              + f"  (mean {sum(iou.values()) / len(iou):.3f})")
    n_img = len({(e.scene_id, e.im_id) for e in est})
    if est:
        ms = 1000 * sum({(e.scene_id, e.im_id): e.time_s for e in est}.values()) / len(est)
        print(f"{len(est)} estimates on {n_img} images, {ms:.1f} ms per object ({args.device})")
    else:
        print("no estimates (no instance had enough depth points)", file=sys.stderr)
    print(f"results: {args.out}")
    return 0
