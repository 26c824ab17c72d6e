"""Depth filtering baselines the thesis compares its refinement with (Table 3.3).

- :func:`guided_filter_depth`: the guided filter [HST12] with the color image (gray) as guide. Missing
  depth is handled by normalised filtering: ``GF(D * M) / GF(M)`` (the filter is linear in its input),
  which also fills holes where at least ``min_support`` of the window had depth (measured pixels
  always keep a filtered depth).
- :func:`median_filter_depth`: a plain ``k x k`` median of the valid depths of each window [ACD+09]
  (invalid pixels ignored; a missing pixel is filled when more than half the window is valid).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

__all__ = ["GuidedFilterConfig", "guided_filter_depth", "MedianFilterConfig", "median_filter_depth"]


@dataclass(frozen=True)
class GuidedFilterConfig:
    radius_px: int = 4
    """Window radius r (window (2r+1)^2)."""
    eps: float = 1e-3
    """Regularisation epsilon (guide intensities in [0, 1])."""
    min_support: float = 0.5
    """A missing pixel gets a depth only where the filtered validity mask is at least this."""


@dataclass(frozen=True)
class MedianFilterConfig:
    ksize: int = 5
    """Window side k (odd)."""


def _check(color: np.ndarray, depth_m: np.ndarray) -> None:
    if depth_m.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth_m.shape}")
    if color is not None and (color.shape != depth_m.shape + (3,) or color.dtype != np.uint8):
        raise ValueError(f"color must be uint8 {depth_m.shape + (3,)}, got {color.dtype} {color.shape}")


def _box(x: np.ndarray, r: int) -> np.ndarray:
    return cv2.boxFilter(x, cv2.CV_64F, (2 * r + 1, 2 * r + 1), normalize=True, borderType=cv2.BORDER_REFLECT)


def _guided(I: np.ndarray, p: np.ndarray, r: int, eps: float) -> np.ndarray:
    mI, mp = _box(I, r), _box(p, r)
    cov = _box(I * p, r) - mI * mp
    var = _box(I * I, r) - mI * mI
    a = cov / (var + eps)
    b = mp - a * mI
    return _box(a, r) * I + _box(b, r)


def guided_filter_depth(color: np.ndarray, depth_m: np.ndarray,
                        config: GuidedFilterConfig = GuidedFilterConfig()) -> np.ndarray:
    """Guided filter of a depth map (float32 (H,W) metres, 0 = invalid) guided by uint8 (H,W,3) color.

    Returns float32 (H, W), 0 where unsupported."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    _check(color, depth_m)
    I = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0
    M = (depth_m > 0).astype(np.float64)
    num = _guided(I, depth_m.astype(np.float64) * M, config.radius_px, config.eps)
    den = _guided(I, M, config.radius_px, config.eps)
    out = np.zeros(depth_m.shape, np.float32)
    # Measured pixels always keep a (filtered) depth; missing ones are filled only with support.
    ok = (den >= config.min_support) | ((M > 0) & (den > 1e-3))
    out[ok] = (num[ok] / den[ok]).astype(np.float32)
    out[out < 0] = 0
    return out


@nb.njit(cache=True, parallel=True)
def _masked_median_nb(D, r):
    H, W = D.shape
    out = np.zeros((H, W), np.float32)
    for v in nb.prange(H):
        buf = np.empty((2 * r + 1) * (2 * r + 1), np.float32)
        for u in range(W):
            n = 0
            tot = 0
            for qv in range(max(0, v - r), min(H, v + r + 1)):
                for qu in range(max(0, u - r), min(W, u + r + 1)):
                    tot += 1
                    if D[qv, qu] > 0:
                        buf[n] = D[qv, qu]
                        n += 1
            if n == 0 or (D[v, u] <= 0 and 2 * n <= tot):
                continue
            s = np.sort(buf[:n])
            out[v, u] = s[n // 2] if n % 2 == 1 else 0.5 * (s[n // 2 - 1] + s[n // 2])
    return out


def median_filter_depth(depth_m: np.ndarray, config: MedianFilterConfig = MedianFilterConfig()) -> np.ndarray:
    """Median of the valid depths in each ``k x k`` window (float32 (H,W) metres, 0 = invalid)."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    _check(None, depth_m)
    if config.ksize < 1 or config.ksize % 2 == 0:
        raise ValueError(f"ksize must be odd and positive, got {config.ksize}")
    return _masked_median_nb(np.ascontiguousarray(depth_m), config.ksize // 2)
