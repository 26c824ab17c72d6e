"""Feathering of a coverage mask: a weight that is 0 outside the covered pixels and ramps up to 1 over ``feather_px``
inside their border (a box filter of the coverage), in float (:func:`feather_map`) and as integer box counts
(:func:`coverage_counts`, what the blend kernels evaluate: equal bit for bit, tested)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["feather_map", "feather_box", "coverage_counts"]


def feather_map(depth_m: np.ndarray, feather_px: float) -> np.ndarray:
    """Feathering factor of a view's coverage (float32 (H, W), 0 outside): ``clip(2 m - 1, 0, 1)`` of the covered
    fraction ``m`` in a ``feather_px`` box (0 at a straight border, 1 from ``feather_px / 2`` inside)."""
    cov = (depth_m > 0).astype(np.float32)
    if feather_px <= 1:
        return cov
    k = feather_box(feather_px)
    m = cv2.blur(cov, (k, k), borderType=cv2.BORDER_REPLICATE)
    f = np.clip(2.0 * m - 1.0, 0.0, 1.0)
    f *= cov
    return f


def feather_box(feather_px: float) -> int:
    """Side of :func:`feather_map`'s box filter (odd, >= 3)."""
    return max(3, int(round(feather_px)) | 1)


def coverage_counts(depth_m: np.ndarray, feather_px: float, out: np.ndarray | None = None,
                    coverage: np.ndarray | None = None) -> np.ndarray:
    """Integer form of :func:`feather_map`: covered pixels in the ``feather_box`` box (border replicated), uint8
    (uint16 for boxes over 15 px). :func:`feather_map` equals ``clip(2 * float32(count * (1 / box**2)) - 1, 0, 1)``
    on covered pixels bit for bit (tested), which the blend kernel evaluates. ``coverage``: ``depth_m > 0`` uint8."""
    k = feather_box(feather_px)
    dt = np.uint8 if k * k <= 255 else np.uint16
    cov = (depth_m > 0).view(np.uint8) if coverage is None else coverage
    if out is None:
        out = np.empty(depth_m.shape, dt)
    cv2.boxFilter(cov, cv2.CV_8U if dt == np.uint8 else cv2.CV_16U, (k, k), dst=out, normalize=False,
                  borderType=cv2.BORDER_REPLICATE)
    return out
