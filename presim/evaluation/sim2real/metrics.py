"""Depth metrics of Table 4.3 (thesis §4.5) on real test frames, where the sensor depth is valid.

All valid pixels of all frames of a group are pooled (as DenseDepth's evaluation does):

- ``rms``    = sqrt(mean((pred - gt)^2)), metres;
- ``absrel`` = mean(|pred - gt| / gt);
- ``delta1`` = fraction of pixels with max(pred / gt, gt / pred) < 1.25.

Valid = ``0 < gt <= max_depth_m``; predictions are clipped to [min_depth_m, max_depth_m] first.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DepthErrorSums", "depth_metrics"]


class DepthErrorSums:
    """Running sums for pooled metrics over many frames (one per group: bin or overall)."""

    def __init__(self) -> None:
        self.n = 0
        self.sq = 0.0
        self.rel = 0.0
        self.d1 = 0

    def add(self, pred: np.ndarray, gt: np.ndarray, min_depth_m: float = 0.1, max_depth_m: float = 10.0) -> None:
        pred = np.asarray(pred, np.float64)
        gt = np.asarray(gt, np.float64)
        if pred.shape != gt.shape:
            raise ValueError(f"pred {pred.shape} and gt {gt.shape} differ in shape")
        m = (gt > 0) & (gt <= max_depth_m)
        p = np.clip(pred[m], min_depth_m, max_depth_m)
        g = gt[m]
        self.n += int(m.sum())
        self.sq += float(((p - g) ** 2).sum())
        self.rel += float((np.abs(p - g) / g).sum())
        self.d1 += int((np.maximum(p / g, g / p) < 1.25).sum())

    def merge(self, other: "DepthErrorSums") -> None:
        """Add another group's sums (pooling: the result is as if its pixels had been added here)."""
        self.n += other.n
        self.sq += other.sq
        self.rel += other.rel
        self.d1 += other.d1

    def result(self) -> dict:
        if self.n == 0:
            return {"rms": float("nan"), "absrel": float("nan"), "delta1": float("nan"), "n_pixels": 0}
        return {"rms": float(np.sqrt(self.sq / self.n)), "absrel": self.rel / self.n,
                "delta1": self.d1 / self.n, "n_pixels": self.n}


def depth_metrics(pred: np.ndarray, gt: np.ndarray, min_depth_m: float = 0.1, max_depth_m: float = 10.0) -> dict:
    """``{"rms", "absrel", "delta1", "n_pixels"}`` of ``pred`` against ``gt`` (same shape, any number
    of frames), on the pixels where ``0 < gt <= max_depth_m``."""
    s = DepthErrorSums()
    s.add(pred, gt, min_depth_m, max_depth_m)
    return s.result()
