"""Training loop of the pose and segmentation networks (``presim pose-train``).

A run folder holds ``config.json`` (what was trained: model, sizes, data, objects),
``checkpoint_last.pt`` (written atomically after every epoch: weights, optimiser, epoch, metric rows),
``metrics.csv`` and ``learning_curve.png``. Running again on the same folder resumes after the last
finished epoch (``--epochs`` may be raised; anything else changed is refused). Checkpoints are read with
``torch.load(..., weights_only=True)``. A non-finite loss stops training with
:class:`TrainingDiverged`; the last checkpoint (the last good epoch) is left as it was.

Example:
    >>> report = train("out/bop", "runs/cgaf", TrainConfig(model="cgaf", epochs=2))   # doctest: +SKIP
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from presim.io_utils import atomic_write_bytes, atomic_write_json, atomic_write_text, progress
from presim.pose.nets.checkpoint import CHECKPOINT, load_checkpoint, load_run, save_checkpoint
from presim.pose.nets.data import PoseDataConfig, PoseInstanceDataset
from presim.pose.nets.loss import LossConfig, point_distances, pose_loss, symmetric_add
from presim.pose.nets.models import ARCHS, ModelConfig, PoseNet, best_pose
from presim.pose.nets.segmentation import SegTask

__all__ = ["TrainConfig", "TrainReport", "TrainingDiverged", "train", "load_run", "save_checkpoint",
           "load_checkpoint", "MODELS"]

MODELS = ARCHS + ("segmentation",)


class TrainingDiverged(ValueError):
    """The loss became NaN/inf; the message names the epoch, step and the checkpoint kept."""


QUICK_STEPS = 2500
"""Optimiser steps of the quick recipe (batch 16): sized to fit 20 min on an idle 2-core machine,
see docs/pose-networks.md (measured CPU time per step)."""
QUICK_SEG_EPOCHS = 12
"""Epochs of the segmentation network's quick recipe (whole images per step). On the sample scene's
300-image split: 12 epochs (216 steps, 8 min CPU) reach test object IoU 0.801, where 3 epochs gave
0.645 with the training IoU still climbing (docs/pose-networks.md)."""
QUICK_LR = 1e-3
"""Peak learning rate of the pose networks' quick recipe (``TrainConfig.lr`` left unset)."""
QUICK_SEG_LR = 3e-3
"""Peak learning rate of the segmentation quick recipe (``TrainConfig.lr`` left unset with
``model="segmentation"``): 12 epochs of whole images need a larger step than the pose networks'
2500 instance batches (docs/pose-networks.md)."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Defaults = the CPU quick recipe (what ``pose-train`` does without ``--epochs``)."""

    model: str = "cgaf"
    """``densefusion`` | ``cgaf`` | ``cgaf-noatt`` | ``segmentation``."""
    epochs: int = 0
    """Passes over the training instances; 0 = the quick recipe's fixed budget of ``steps`` optimiser
    steps (segmentation: ``QUICK_SEG_EPOCHS`` epochs)."""
    steps: int = QUICK_STEPS
    """Optimiser steps when ``epochs`` is 0 (checkpoints still come after every pass over the data)."""
    batch_size: int = 16
    """Instances per step."""
    lr: float | None = None
    """Peak Adam learning rate (thesis: 1e-4 for the full recipe; the short CPU recipe needs a larger one).
    None = the quick recipe's rate for ``model``: ``QUICK_SEG_LR`` for segmentation, ``QUICK_LR``
    otherwise (resolved when the config is made, so ``config.json`` records the number)."""
    lr_schedule: str = "cosine"
    """``cosine``: linear warm-up over ``warmup_frac`` of the steps, then cosine decay to 0 at the last
    step; ``constant``: ``lr`` throughout."""
    warmup_frac: float = 0.03
    """Warm-up share of the steps (``cosine``)."""
    seed: int = 0
    """Weights, sampling and augmentation seed."""
    device: str = "cpu"
    """``cpu`` or ``cuda``."""
    threads: int = 2
    """``torch.set_num_threads`` for CPU training (0 = leave torch's default)."""
    full_size: bool = False
    """Published network sizes (GPU recipe) instead of the CPU quick sizes."""
    refine_steps: int = 0
    """The last ``refine_steps`` of the steps train the refiner alone, on the frozen estimator's
    poses (DenseFusion trains its refiner after the estimator converges). 0 = no refiner training; then
    ``pose-predict`` applies no refinement by default (an untrained refiner is the identity)."""
    max_instances: int = 0
    """Use at most this many training instances (0 = all), evenly spread over the split."""
    data: PoseDataConfig = field(default_factory=lambda: PoseDataConfig(augment=True, n_points=128, crop_px=32,
                                                                        n_model_points=100))
    """Instances and augmentation (quick: 128 points, 32 px crop, 100 model points)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss weights."""

    def __post_init__(self) -> None:
        if self.lr is None:
            object.__setattr__(self, "lr", QUICK_SEG_LR if self.model == "segmentation" else QUICK_LR)
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"TrainConfig: lr must be a positive number, got {self.lr}")

    def total_steps(self, steps_per_epoch: int) -> int:
        """Optimiser steps of the whole run."""
        if self.epochs > 0:
            return self.epochs * steps_per_epoch
        if self.model == "segmentation":
            return QUICK_SEG_EPOCHS * steps_per_epoch
        return self.steps

    def lr_at(self, step: int, total: int) -> float:
        """Learning rate of optimiser step ``step`` (0-based) of ``total``."""
        if self.lr_schedule == "constant":
            return self.lr
        if self.lr_schedule != "cosine":
            raise ValueError(f"lr_schedule: unknown schedule '{self.lr_schedule}' (cosine | constant)")
        warm = max(1, int(round(self.warmup_frac * total)))
        if step < warm:
            return self.lr * (step + 1) / warm
        return 0.5 * self.lr * (1.0 + math.cos(math.pi * min(1.0, (step - warm) / max(1, total - warm))))

    def model_config(self, n_objects: int) -> ModelConfig:
        return ModelConfig.full(self.model, n_objects) if self.full_size else ModelConfig(arch=self.model, n_objects=n_objects)


@dataclass
class TrainReport:
    run_dir: Path
    epochs_done: int
    rows: list[dict]
    """One metrics row per epoch (the CSV)."""
    resumed_from: int
    """Epochs that were already done when this call started."""


def _config_json(cfg: TrainConfig, dataset: Path, obj_ids, model_cfg) -> dict:
    d = asdict(cfg)
    d["dataset"] = str(Path(dataset).resolve())
    d["obj_ids"] = [int(o) for o in obj_ids]
    d["model_config"] = asdict(model_cfg) if model_cfg is not None else None
    return json.loads(json.dumps(d))  # tuples -> lists, as read back


def _check_resume(run_dir: Path, new: dict) -> None:
    with open(run_dir / "config.json", encoding="utf-8") as f:
        old = json.load(f)
    free = ("epochs", "steps", "device", "threads")
    a = {k: v for k, v in old.items() if k not in free}
    b = {k: v for k, v in new.items() if k not in free}
    if a != b:
        diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        raise ValueError(f"{run_dir}: holds a run with different settings ({', '.join(diff)}); "
                         "use another --out to start a new run")


# ---- metrics files ----------------------------------------------------------------------------

def _write_metrics(run_dir: Path, rows: list[dict]) -> None:
    if not rows:
        return
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write_text(run_dir / "metrics.csv", buf.getvalue())
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [r["epoch"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].plot(ep, [r["loss"] for r in rows], "o-")
    ax[0].set_xlabel("epoch"), ax[0].set_ylabel("training loss"), ax[0].grid(alpha=0.3)
    for k in [k for k in rows[0] if k not in ("epoch", "step", "loss", "seconds", "cpu_seconds", "instances")]:
        ax[1].plot(ep, [r[k] for r in rows], "o-", label=k)
    ax[1].set_xlabel("epoch"), ax[1].legend(fontsize=7), ax[1].grid(alpha=0.3)
    fig.tight_layout()
    buf2 = io.BytesIO()
    fig.savefig(buf2, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(run_dir / "learning_curve.png", buf2.getvalue())


# ---- the loop ---------------------------------------------------------------------------------

def _subset(n: int, max_n: int) -> list[int]:
    if max_n <= 0 or max_n >= n:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, max_n).round().astype(int).tolist()))


def _refine_dist(cfg: TrainConfig, R, t, batch) -> torch.Tensor:
    if cfg.loss.symmetry == "transforms":
        return symmetric_add(R[:, None], t[:, None], batch["model_points"], batch["sym_targets"])[:, 0]
    return point_distances(R[:, None], t[:, None], batch["model_points"], batch["target"], batch["symmetric"])[:, 0]


def _pose_step(net: PoseNet, batch: dict, cfg: TrainConfig, refine: bool):
    """Estimator loss, or (``refine``) the refiner's loss on the frozen estimator's most confident pose."""
    with torch.set_grad_enabled(not refine):
        out = net(batch["rgb"], batch["points"], batch["choose"], batch["obj_idx"])
        lo = pose_loss(out.R, out.t, out.conf, batch["model_points"], batch["target"], batch["symmetric"], cfg.loss,
                       sym_targets=batch["sym_targets"])
    loss = lo.loss
    R, t, _ = best_pose(out)
    R, t = R.detach(), t.detach()
    d_ref = lo.best_dist_m.detach()
    if refine:
        loss = 0.0
        for _ in range(net.cfg.refine_iters):
            R, t = net.refine(batch["points"], out.emb.detach(), batch["obj_idx"], R.detach(), t.detach())
            d = _refine_dist(cfg, R, t, batch)
            loss = loss + d.mean()
            d_ref = d.detach()
    return loss, {"add_m": lo.best_dist_m.detach(), "add_refined_m": d_ref, "diameter_m": batch["diameter_m"]}


def train(dataset: str | Path, run_dir: str | Path, cfg: TrainConfig = TrainConfig(),
          show_progress: bool = True, max_steps: int = 0) -> TrainReport:
    """Train ``cfg.model`` on the ``cfg.data.split`` instances of BOP folder ``dataset`` into ``run_dir``.

    ``max_steps`` > 0 stops after that many optimiser steps in total (tests, smoke runs).
    """
    if cfg.model not in MODELS:
        raise ValueError(f"--model: unknown model '{cfg.model}' (choose from {', '.join(MODELS)})")
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available to torch here")
    run_dir = Path(run_dir)
    if cfg.threads > 0 and not cfg.device.startswith("cuda"):
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    if cfg.model == "segmentation":
        task = SegTask(dataset, cfg)
    else:
        task = _PoseTask(dataset, cfg)
    drop_last = len(task.train_set) > cfg.batch_size
    spe = max(1, len(task.train_set) // cfg.batch_size if drop_last else 1)
    total = cfg.total_steps(spe)
    if cfg.model != "segmentation" and cfg.refine_steps >= total:
        raise ValueError(f"--refine-steps: {cfg.refine_steps} is not below the run's {total} optimiser steps "
                         "(the estimator must train first)")
    conf_json = _config_json(cfg, dataset, task.obj_ids, task.model_cfg)
    resumed, rows = 0, []
    net, opt = task.net.to(cfg.device), torch.optim.Adam(task.net.parameters(), lr=cfg.lr)
    if (run_dir / CHECKPOINT).is_file():
        _check_resume(run_dir, conf_json)
        ck = load_checkpoint(run_dir / CHECKPOINT, cfg.device)
        net.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        resumed = int(ck["epoch"])
        rows = [dict(r) for r in ck["rows"]]
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(run_dir / "config.json", conf_json)
    n_epochs = math.ceil(total / spe)
    gstep = int(rows[-1].get("step", resumed * spe)) if rows else 0  # optimiser steps already done
    if resumed < n_epochs and hasattr(task, "prepare"):
        task.prepare(show_progress)
    step = 0
    for epoch in range(resumed, n_epochs):
        task.dataset.set_epoch(epoch)
        g = torch.Generator().manual_seed(cfg.seed * 1000 + epoch)
        loader = torch.utils.data.DataLoader(task.train_set, batch_size=cfg.batch_size, shuffle=True,
                                             generator=g, num_workers=0, drop_last=drop_last)
        net.train()
        t0, c0, losses, stats = time.perf_counter(), time.process_time(), [], {}
        bar = progress(loader, desc=f"{cfg.model} epoch {epoch + 1}/{n_epochs}", unit="batch",
                       disable=None if show_progress else True)
        for batch in bar:
            if gstep >= total:
                break
            batch = {k: v.to(cfg.device) for k, v in batch.items()}
            for grp in opt.param_groups:
                grp["lr"] = cfg.lr_at(gstep, total)
            loss, st = task.step(net, batch, gstep, total)
            if not torch.isfinite(loss):
                kept = (f"last good checkpoint {run_dir / CHECKPOINT} (epoch {resumed_or(rows)}) kept"
                        if (run_dir / CHECKPOINT).is_file() else "no checkpoint was written yet")
                raise TrainingDiverged(f"{cfg.model}: loss is {loss.item()} at epoch {epoch + 1} step {step + 1}; "
                                       f"training stopped, {kept} (lower --lr or check the data)")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
            opt.step()
            losses.append(loss.item())
            for k, v in st.items():
                stats.setdefault(k, []).append(v.cpu())
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
            step += 1
            gstep += 1
            if max_steps and step >= max_steps:
                break
        if not losses:
            break
        row = {"epoch": epoch + 1, "step": gstep, "loss": float(np.mean(losses)), **task.summarise(stats),
               "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
               "instances": len(task.train_set)}
        rows.append(row)
        save_checkpoint(run_dir / CHECKPOINT, {"model": net.state_dict(), "optimizer": opt.state_dict(),
                                               "epoch": epoch + 1, "rows": rows})
        _write_metrics(run_dir, rows)
        if (max_steps and step >= max_steps) or gstep >= total:
            break
    return TrainReport(run_dir=run_dir, epochs_done=len(rows), rows=rows, resumed_from=resumed)


def resumed_or(rows: list[dict]) -> int:
    return int(rows[-1]["epoch"]) if rows else 0


class _PoseTask:
    """Dataset, network and per-step loss of a pose model."""

    def __init__(self, dataset, cfg: TrainConfig):
        self.cfg = cfg
        self.dataset = PoseInstanceDataset(dataset, cfg.data)
        self.train_set = torch.utils.data.Subset(self.dataset, _subset(len(self.dataset), cfg.max_instances))
        self.obj_ids = self.dataset.objects.obj_ids
        self.model_cfg = cfg.model_config(len(self.obj_ids))
        self.net = PoseNet(self.model_cfg)

    def prepare(self, show_progress: bool) -> None:
        """Read every training instance once into the dataset's cache."""
        self.dataset.precompute(self.train_set.indices, show_progress)

    def step(self, net, batch, step: int, total: int):
        return _pose_step(net, batch, self.cfg, refine=step >= total - self.cfg.refine_steps)

    @staticmethod
    def summarise(stats: dict) -> dict:
        a, r, d = (torch.cat(stats[k]) for k in ("add_m", "add_refined_m", "diameter_m"))
        return {"add_m": float(a.mean()), "add_refined_m": float(r.mean()),
                "acc_01d": float((a < 0.1 * d).float().mean()), "acc_01d_refined": float((r < 0.1 * d).float().mean())}


def quick_recipe_note() -> str:
    return "quick CPU recipe: " + ", ".join(f"{k}={v}" for k, v in asdict(TrainConfig()).items() if k != "data")
