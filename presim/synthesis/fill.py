"""Final fill of pixels no view covered; they stay ``valid=False``.

``"telea"`` inpaints colour (:func:`presim.imaging.inpaint.telea_inpaint`, reference ``cv2.inpaint``), ``"pushpull"``
pull-pushes (:func:`presim.imaging.pushpull.pushpull_rgbd`, reference :func:`presim.imaging.pushpull.pushpull_fill`);
``"auto"`` uses telea below ``telea_max_hole_frac`` of the image. Depth is pull-pushed."""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from presim.imaging.inpaint import telea_inpaint
from presim.imaging.pushpull import pushpull_rgbd
from presim.synthesis.config import FILL_METHODS

__all__ = ["foreground_rim", "fill_holes"]


def foreground_rim(depth_m: np.ndarray, valid: np.ndarray, rim_px: int = 4, depth_tol: float = 0.05) -> np.ndarray:
    """bool (H, W): the known pixels within ``rim_px`` of a hole that lie in front of the hole's background by more than
    ``depth_tol`` (relative): the foreground side of a disocclusion, which a fill should not continue into the hole (the
    hole hides what is behind the object). A hole's background depth is the 90th percentile of the known depths of its
    rim (per 8-connected component of the holes grown by ``rim_px``). ``rim_px`` 0: none."""
    holes = (~valid).view(np.uint8)
    if rim_px <= 0 or not holes.any():
        return np.zeros(valid.shape, bool)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * rim_px + 1, 2 * rim_px + 1))
    grown = cv2.dilate(holes, k)
    rim = grown.view(bool) & valid
    n, labels = cv2.connectedComponents(grown, connectivity=8)
    lab, d = labels[rim], depth_m[rim]
    order = np.lexsort((d, lab))
    lab, d = lab[order], d[order]
    starts = np.searchsorted(lab, np.arange(n))
    ends = np.searchsorted(lab, np.arange(n), side="right")
    bg = np.zeros(n, np.float32)
    has = ends > starts
    bg[has] = d[np.minimum(starts[has] + ((ends[has] - starts[has] - 1) * 9) // 10, len(d) - 1)]
    out = np.zeros(valid.shape, bool)
    out[rim] = depth_m[rim] < bg[labels[rim]] * np.float32(1.0 - depth_tol)
    return out


def fill_holes(color: np.ndarray, depth_m: np.ndarray, valid: np.ndarray, method: str = "auto",
               telea_max_hole_frac: float = 0.02, background_rim_px: int = 0,
               pushpull: Callable = pushpull_rgbd) -> tuple[np.ndarray, np.ndarray]:
    """Fill ``color`` (uint8 (H, W, 3)) and ``depth_m`` (float32) where ``valid`` is False: new arrays.
    ``background_rim_px`` > 0: :func:`foreground_rim` pixels neither feed the colour fill nor change. ``pushpull``: the
    pull-push kernel (:func:`~presim.imaging.pushpull.pushpull_rgbd`'s contract; the torch backend's); Telea and the rim
    run on the host."""
    if method not in FILL_METHODS:
        raise ValueError(f"fill method must be one of {FILL_METHODS}, got {method!r}")
    holes = ~valid
    n_hole = holes.size - int(np.count_nonzero(valid))
    if n_hole == 0 or n_hole == holes.size:
        return color.copy(), depth_m.copy()
    if method == "auto":
        method = "telea" if n_hole / holes.size <= telea_max_hole_frac else "pushpull"
    rim = foreground_rim(depth_m, valid, background_rim_px) if background_rim_px > 0 else None
    if rim is not None and rim.any():
        src = valid & ~rim  # the fill reads the background side only
        out_c = telea_inpaint(color, ~src, 3) if method == "telea" else pushpull(color, depth_m, src)[0]
        out_c[rim] = color[rim]
        return out_c, pushpull(None, depth_m, valid)[1]
    if method == "telea":
        return telea_inpaint(color, holes, 3), pushpull(None, depth_m, valid)[1]
    return pushpull(color, depth_m, valid)
