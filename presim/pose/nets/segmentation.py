"""Segmentation network in front of the pose networks (thesis §4.4/Table 4.4, §6.4).

A small U-Net-style encoder-decoder (3 down-sampling stages with skip connections, GroupNorm, random
init) labels every pixel of an image with 0 = background or 1 + the object's index in
``models_info.json``; trained with cross-entropy on the ground-truth visible masks of a BOP split,
at ``scale`` of the image size. At test time :func:`segment` gives a full-resolution label map, and
pose-predict makes one instance per object id found in it.

Example:
    >>> net, cfg = load_seg_net("runs/seg")                       # doctest: +SKIP
    >>> labels = segment(net, cfg, rgb)                           # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from presim.datasets.bop_reader import BopDataset
from presim.pose.nets.checkpoint import load_run
from presim.pose.nets.data import IMAGENET_MEAN, IMAGENET_STD

__all__ = ["SegConfig", "SegNet", "SegImageDataset", "SegTask", "segment", "load_seg_net", "segmentation_iou"]


@dataclass(frozen=True)
class SegConfig:
    """Sizes of the segmentation network."""

    n_classes: int = 2
    """1 + number of objects."""
    width: int = 16
    """Channels of the first stage (x2 per stage)."""
    scale: float = 0.5
    """Images are resized by this before the network (sides rounded to a multiple of 8)."""
    background_weight: float = 0.1
    """Cross-entropy weight of the background class (objects: 1). Objects cover a few % of the
    pixels; with weight 1 two short epochs on the sample scene predicted background everywhere
    (object mIoU 0.000 after 74 steps)."""


def _size(h: int, w: int, scale: float) -> tuple[int, int]:
    return max(8, int(round(h * scale / 8)) * 8), max(8, int(round(w * scale / 8)) * 8)


def _block(cin, cout):
    g = 8 if cout % 8 == 0 else 1
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, bias=False), nn.GroupNorm(g, cout), nn.ReLU(),
                         nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.GroupNorm(g, cout), nn.ReLU())


class SegNet(nn.Module):
    """(B, 3, H, W) normalised colour -> (B, n_classes, H, W) logits; H, W multiples of 8."""

    def __init__(self, cfg: SegConfig):
        super().__init__()
        w = cfg.width
        self.enc = nn.ModuleList([_block(3, w), _block(w, 2 * w), _block(2 * w, 4 * w), _block(4 * w, 8 * w)])
        self.dec = nn.ModuleList([_block(8 * w + 4 * w, 4 * w), _block(4 * w + 2 * w, 2 * w), _block(2 * w + w, w)])
        self.out = nn.Conv2d(w, cfg.n_classes, 1)

    def forward(self, x):
        skips = []
        for i, e in enumerate(self.enc):
            x = e(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for d, s in zip(self.dec, reversed(skips[:-1])):
            x = d(torch.cat([F.interpolate(x, size=s.shape[-2:], mode="bilinear", align_corners=False), s], 1))
        return self.out(x)


def _prep(rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    x = cv2.resize(rgb, (hw[1], hw[0]), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return ((x - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1).copy()


class SegImageDataset(torch.utils.data.Dataset):
    """Images of a BOP split with label maps from the visible masks (later instances drawn on top)."""

    def __init__(self, root, split: str, obj_ids: tuple[int, ...], cfg: SegConfig, augment: bool, seed: int):
        self.bop, self.cfg, self.obj_ids, self.augment, self.seed = BopDataset(root, split), cfg, obj_ids, augment, seed
        self.items = [(s, i) for s in self.bop.scene_ids() for i in sorted(self.bop.scene_gt(s))]
        if not self.items:
            raise ValueError(f"{self.bop.split_dir}: no annotated images")
        self._epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self._epoch = int(epoch)

    def __len__(self):
        return len(self.items)

    def labels(self, sid: int, im_id: int) -> np.ndarray:
        """(H, W) int64 label map at full resolution."""
        lab = None
        for k, g in enumerate(self.bop.scene_gt(sid)[im_id]):
            p = self.bop.mask_path(sid, im_id, k)
            if not p.is_file():
                continue
            m = self.bop.read_mask(sid, im_id, k)
            if lab is None:
                lab = np.zeros(m.shape, np.int64)
            lab[m] = self.obj_ids.index(g.obj_id) + 1
        if lab is None:
            h, w = self.bop.read_rgb(sid, im_id).shape[:2]
            lab = np.zeros((h, w), np.int64)
        return lab

    def __getitem__(self, i):
        sid, im_id = self.items[i]
        rgb = self.bop.read_rgb(sid, im_id)
        if self.augment:
            rng = np.random.default_rng([self.seed, self._epoch, i])
            rgb = np.clip(rgb.astype(np.float32) * rng.uniform(0.8, 1.2) * (1 + rng.uniform(-0.05, 0.05, 3)),
                          0, 255).astype(np.uint8)
        hw = _size(*rgb.shape[:2], self.cfg.scale)
        lab = cv2.resize(self.labels(sid, im_id).astype(np.uint8), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
        return {"rgb": torch.as_tensor(_prep(rgb, hw)), "labels": torch.as_tensor(lab.astype(np.int64))}


def _iou_counts(pred: torch.Tensor, lab: torch.Tensor, n: int) -> torch.Tensor:
    """(n, 2) intersection and union pixel counts per class."""
    out = torch.zeros(n, 2)
    for c in range(n):
        p, g = pred == c, lab == c
        out[c, 0], out[c, 1] = (p & g).sum(), (p | g).sum()
    return out


class SegTask:
    """The segmentation network as a :func:`presim.pose.nets.train.train` task."""

    def __init__(self, dataset, cfg):
        bop = BopDataset(dataset, cfg.data.split)
        self.obj_ids = tuple(sorted(bop.models_info()))
        self.model_cfg = SegConfig(n_classes=len(self.obj_ids) + 1)
        self.dataset = SegImageDataset(dataset, cfg.data.split, self.obj_ids, self.model_cfg, True, cfg.seed)
        self.train_set = self.dataset
        self.net = SegNet(self.model_cfg)

    def step(self, net, batch, step, total):
        logits = net(batch["rgb"])
        w = torch.ones(logits.shape[1], device=logits.device)
        w[0] = self.model_cfg.background_weight
        loss = F.cross_entropy(logits, batch["labels"], weight=w)
        return loss, {"iou": _iou_counts(logits.argmax(1).detach(), batch["labels"], logits.shape[1])[None]}

    def summarise(self, stats):
        c = torch.cat(stats["iou"]).sum(0)
        iou = c[:, 0] / c[:, 1].clamp_min(1)
        return {"miou_objects": float(iou[1:].mean()), "iou_background": float(iou[0])}


def load_seg_net(run_dir: str | Path, device: str = "cpu") -> tuple[SegNet, dict]:
    cfg, ck = load_run(run_dir)
    if cfg.get("model") != "segmentation":
        raise ValueError(f"{run_dir}: is a '{cfg.get('model')}' run; --segmentation takes a segmentation run")
    net = SegNet(SegConfig(**cfg["model_config"]))
    net.load_state_dict(ck["model"])
    return net.to(device).eval(), cfg


@torch.no_grad()
def segment(net: SegNet, run_cfg: dict, rgb: np.ndarray, device: str = "cpu") -> np.ndarray:
    """(H, W, 3) uint8 -> (H, W) int64 labels (0 = background, 1 + object index)."""
    sc = SegConfig(**run_cfg["model_config"])
    hw = _size(*rgb.shape[:2], sc.scale)
    logits = net(torch.as_tensor(_prep(rgb, hw))[None].to(device))
    logits = F.interpolate(logits, size=rgb.shape[:2], mode="bilinear", align_corners=False)
    return logits.argmax(1)[0].cpu().numpy()


def segmentation_iou(dataset, run_dir, split: str = "test", device: str = "cpu") -> dict[int, float]:
    """Per-object IoU (Table 4.4) of a segmentation run on a split's visible masks, full resolution."""
    net, cfg = load_seg_net(run_dir, device)
    obj_ids = tuple(cfg["obj_ids"])
    ds = SegImageDataset(dataset, split, obj_ids, SegConfig(**cfg["model_config"]), False, 0)
    tot = torch.zeros(len(obj_ids) + 1, 2)
    for sid, im_id in ds.items:
        pred = torch.as_tensor(segment(net, cfg, ds.bop.read_rgb(sid, im_id), device))
        tot += _iou_counts(pred, torch.as_tensor(ds.labels(sid, im_id)), len(obj_ids) + 1)
    return {o: float(tot[k + 1, 0] / max(float(tot[k + 1, 1]), 1.0)) for k, o in enumerate(obj_ids)}
