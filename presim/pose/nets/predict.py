"""Pose estimates of a trained run on a BOP split, as BOP'19 results (``presim pose-predict``).

For every instance pose-eval scores by default (visible fraction >= 10 %), the network sees the crop,
the masked depth points and the object's id, keeps its most confident per-point pose and refines it
``refine_iters`` times. Masks are the ground-truth visible masks (the upper bound) or, with a
segmentation run, the predicted ones (one instance per object id found in the image). The ``time``
column is the network time of the image (all its objects), seconds.

Example:
    >>> est = predict("out/bop_test", "runs/cgaf", PredictConfig(split="test"))    # doctest: +SKIP
    >>> write_bop_results("results.csv", est)                                      # doctest: +SKIP
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from presim.io_utils import progress
from presim.pose.nets.data import PoseDataConfig, PoseInstanceDataset, make_instance
from presim.pose.nets.checkpoint import load_run
from presim.pose.nets.models import ModelConfig, PoseNet, best_pose
from presim.pose.nets.segmentation import load_seg_net, segment
from presim.pose.results import Estimate

__all__ = ["PredictConfig", "load_pose_net", "predict"]


@dataclass(frozen=True)
class PredictConfig:
    """What to predict on."""

    split: str = "test"
    """BOP split folder."""
    device: str = "cpu"
    """``cpu`` or ``cuda``."""
    refine_iters: int = -1
    """Refinement iterations (-1 = the run's: 2, or 0 when its refiner was not trained; 0 = the estimator alone)."""
    seed: int = 0
    """Seeds the point sampling."""


def load_pose_net(run_dir: str | Path, device: str = "cpu") -> tuple[PoseNet, dict]:
    """The trained network of a ``pose-train`` run folder and its config.json."""
    cfg, ck = load_run(run_dir)
    if cfg.get("model") == "segmentation":
        raise ValueError(f"{run_dir}: is a segmentation run; --checkpoint takes a pose model run")
    mc = dict(cfg["model_config"])
    mc["geo_dims"], mc["head_dims"] = tuple(mc["geo_dims"]), tuple(mc["head_dims"])
    net = PoseNet(ModelConfig(**mc))
    net.load_state_dict(ck["model"])
    return net.to(device).eval(), cfg


def _data_cfg(run_cfg: dict, cfg: PredictConfig) -> PoseDataConfig:
    d = dict(run_cfg["data"])
    return replace(PoseDataConfig(**d), split=cfg.split, augment=False, seed=cfg.seed)


@torch.no_grad()
def _estimate(net: PoseNet, inst: dict, obj_idx: int, iters: int, device: str):
    rgb = torch.as_tensor(inst["rgb"])[None].to(device)
    pts = torch.as_tensor(inst["points"])[None].to(device)
    ch = torch.as_tensor(inst["choose"])[None].to(device)
    oi = torch.tensor([obj_idx], device=device)
    out = net(rgb, pts, ch, oi)
    R, t, c = best_pose(out)
    for _ in range(iters):
        R, t = net.refine(pts, out.emb, oi, R, t)
    return R[0].cpu().double().numpy(), t[0].cpu().double().numpy(), float(c[0])


def predict(dataset: str | Path, run_dir: str | Path, cfg: PredictConfig = PredictConfig(),
            segmentation: str | Path | None = None, show_progress: bool = True) -> list[Estimate]:
    """Estimates for the split's instances (ground-truth masks, or ``segmentation``'s masks)."""
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available to torch here")
    net, run_cfg = load_pose_net(run_dir, cfg.device)
    dcfg = _data_cfg(run_cfg, cfg)
    ds = PoseInstanceDataset(dataset, dcfg)
    if tuple(ds.objects.obj_ids) != tuple(run_cfg["obj_ids"]):
        raise ValueError(f"{dataset}: objects {list(ds.objects.obj_ids)} differ from those the run "
                         f"{run_dir} was trained on {run_cfg['obj_ids']}")
    if cfg.refine_iters >= 0:
        iters = cfg.refine_iters
    else:  # the run's: none when its refiner was never trained (refine_steps 0)
        iters = 0 if run_cfg.get("refine_steps", 1) == 0 else net.cfg.refine_iters
    est_rows: list[tuple] = []
    img_time: dict[tuple[int, int], float] = {}
    if segmentation is None:
        for i in progress(range(len(ds)), desc="pose-predict", unit="inst", disable=None if show_progress else True):
            r = ds.refs[i]
            t0 = time.perf_counter()
            inst = ds.load(i, np.random.default_rng([cfg.seed, i]))
            if inst is None:  # too few depth pixels: no estimate (pose-eval counts it as a miss)
                continue
            R, t, c = _estimate(net, inst, int(inst["obj_idx"]), iters, cfg.device)
            dt = time.perf_counter() - t0
            img_time[(r.scene_id, r.im_id)] = img_time.get((r.scene_id, r.im_id), 0.0) + dt
            est_rows.append((r.scene_id, r.im_id, r.obj_id, c, R, t))
    else:
        seg, seg_cfg = load_seg_net(segmentation, cfg.device)
        if tuple(seg_cfg["obj_ids"]) != tuple(run_cfg["obj_ids"]):
            raise ValueError(f"{segmentation}: segmentation objects {seg_cfg['obj_ids']} differ from the pose "
                             f"run's {run_cfg['obj_ids']}")
        bop = ds.bop
        images = sorted({(r.scene_id, r.im_id) for r in ds.refs})
        for sid, im_id in progress(images, desc="pose-predict (segmentation)", unit="img",
                                   disable=None if show_progress else True):
            t0 = time.perf_counter()
            rgb, depth = bop.read_rgb(sid, im_id), bop.read_depth_m(sid, im_id)
            labels = segment(seg, seg_cfg, rgb, cfg.device)
            K = bop.intrinsics(sid, im_id)
            for k, obj_id in enumerate(ds.objects.obj_ids):
                mask = labels == k + 1
                if mask.sum() < dcfg.min_points:
                    continue
                inst = make_instance(rgb, depth, mask, K, dcfg, np.random.default_rng([cfg.seed, sid, im_id, k]))
                if inst is None:
                    continue
                R, t, c = _estimate(net, inst, k, iters, cfg.device)
                est_rows.append((sid, im_id, obj_id, c, R, t))
            img_time[(sid, im_id)] = time.perf_counter() - t0
    return [Estimate(scene_id=s, im_id=i, obj_id=o, score=c, R=R, t_m=t, time_s=img_time[(s, i)], line=0)
            for s, i, o, c, R, t in est_rows]
