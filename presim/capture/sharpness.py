"""Per-frame sharpness (blur) score of captured images (beyond the thesis).

Motion blur and defocus in a capture frame are copied into every synthesized pixel that frame
wins. :func:`sharpness_score` rates one image with the no-reference **re-blur** measure of
Crété-Roffet et al. (2007, "The blur effect: perception and estimation with a new no-reference
perceptual blur metric"): blur the image again with a 1 x 9 box filter along each axis and measure
how much of its neighbouring-pixel variation survives. A sharp image loses much of its variation
(its edges were steep), an already blurred one loses little. The score is
``1 - max(blur_h, blur_v)`` in [0, 1] (higher = sharper) where, per axis,

    blur = (sum D_F - sum max(0, D_F - D_B)) / sum D_F

with ``D_F`` / ``D_B`` the absolute differences of neighbouring pixels of the image / re-blurred
image. Why this and not the variance of the Laplacian: the re-blur ratio is normalised by the
image's own variation, so it barely depends on contrast, exposure or how much texture a view
contains (a textured and a plain view of one scene, or a dark and a bright frame, are not mistaken
for sharp and blurred), and taking the worse axis catches one-directional motion blur, which a
rotationally symmetric Laplacian averages away. It costs two box filters and four differences on
the grey image (~2 ms at 640x480).

Views of one capture look at similar content, so scores are compared among the candidate views
of a target (:class:`ViewSharpness`, which the renderer uses).
"""

from __future__ import annotations

from typing import Callable, Sequence

import cv2
import numpy as np

__all__ = ["sharpness_score", "ViewSharpness"]


def sharpness_score(color: np.ndarray, box_px: int = 9) -> float:
    """Re-blur sharpness of an RGB (H, W, 3) or grey (H, W) uint8 image, in [0, 1] (higher = sharper)."""
    img = np.asarray(color)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2 or min(img.shape) < box_px + 2:
        raise ValueError(f"sharpness_score needs an image larger than {box_px + 2} px, got shape {img.shape}")
    g = img.astype(np.float32)
    blurs = []
    # axis 0: vertical neighbours, blurred along columns (cv2 ksize is (width, height)); axis 1: horizontal.
    for axis, ksize in ((0, (1, box_px)), (1, (box_px, 1))):
        b = cv2.blur(g, ksize, borderType=cv2.BORDER_REPLICATE)
        df = np.abs(np.diff(g, axis=axis))
        db = np.abs(np.diff(b, axis=axis))
        sf = float(df.sum())
        sv = float(np.maximum(0.0, df - db).sum())
        blurs.append(1.0 if sf <= 0 else (sf - sv) / sf)
    return float(1.0 - max(blurs))


class ViewSharpness:
    """Sharpness-aware views (``RenderConfig.sharpness``): a cached :func:`sharpness_score` per capture frame
    (~2 ms per VGA frame), compared among one target's candidates."""

    def __init__(self, load_color: Callable[[int], np.ndarray], gamma: float = 2.0, demote_frac: float = 0.85):
        self._load_color = load_color
        self.gamma = float(gamma)
        self.demote_frac = float(demote_frac)
        self._scores: dict[int, float] = {}
        self._best = 1.0

    def score(self, v: int) -> float:
        """Sharpness score of view ``v`` (computed on first use)."""
        s = self._scores.get(v)
        if s is None:
            s = self._scores[v] = sharpness_score(self._load_color(v))
        return s

    def order(self, candidates: Sequence[int]) -> np.ndarray:
        """int64 permutation of ``candidates`` moving blurred ones (score < demote_frac x best) behind the sharp
        ones, order kept within each group; sets the best score :meth:`quality` uses."""
        cand = [int(v) for v in candidates]
        if not cand:
            return np.zeros(0, np.int64)
        sc = np.array([self.score(v) for v in cand])
        self._best = max(float(sc.max()), 1e-6)
        blurred = sc < self.demote_frac * self._best
        return np.concatenate([np.flatnonzero(~blurred), np.flatnonzero(blurred)]).astype(np.int64)

    def quality(self, v: int) -> float:
        """Blend weight factor ``(score / best candidate score) ** gamma`` (<= 1)."""
        return float(min(1.0, self.score(v) / self._best) ** self.gamma)
