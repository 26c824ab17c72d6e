"""Gaussian filter of a uint8 colour image, ``sigma`` in pixels (the renderer's reconstruction filter,
:func:`presim.synthesis.pipeline.smooth`; docs/synthesis.md says why it filters and how sigma is fitted).

Reference :func:`smooth_colors_ref` (float64, reflected border, rounding half up); fast path
:func:`smooth_colors` (OpenCV's fixed-point Gaussian, within one grey level of the reference); torch
:func:`presim.imaging.torch_ops.smooth_colors_torch`."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MIN_SIGMA_PX", "kernel_size", "gaussian_taps", "check_smooth_input", "smooth_colors_ref",
           "smooth_colors"]

MIN_SIGMA_PX = 0.1
"""Below this the filter is the identity (its side taps would be < 1e-21)."""


def kernel_size(sigma_px: float) -> int:
    """Odd side of the kernel: ``round(6 sigma + 1) | 1``, at least 3 (OpenCV's rule for uint8)."""
    return max(3, int(round(6.0 * sigma_px + 1.0)) | 1)


def gaussian_taps(sigma_px: float) -> np.ndarray:
    """float64 (k,) normalised 1-D Gaussian taps."""
    k = kernel_size(sigma_px)
    x = np.arange(k) - (k - 1) / 2.0
    t = np.exp(-0.5 * (x / sigma_px) ** 2)
    return t / t.sum()


def check_smooth_input(color: np.ndarray, sigma_px: float) -> None:
    """ValueError unless ``color`` is uint8 (H, W, 3) and ``sigma_px`` a finite number >= 0."""
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"smooth: need uint8 (H, W, 3) colour, got {color.dtype} {color.shape}")
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"smooth: sigma must be a finite number >= 0, got {sigma_px}")


def smooth_colors_ref(color: np.ndarray, sigma_px: float) -> np.ndarray:
    """Separable Gaussian (rows, then columns) in float64 with the border reflected (``dcb|abcd|cba``),
    ``floor(x + 0.5)``. New uint8 (H, W, 3); a copy below :data:`MIN_SIGMA_PX`."""
    check_smooth_input(color, sigma_px)
    if sigma_px < MIN_SIGMA_PX:
        return color.copy()
    t = gaussian_taps(sigma_px)
    r = len(t) // 2
    x = color.astype(np.float64)
    for axis in (1, 0):
        pad = [(0, 0)] * 3
        pad[axis] = (r, r)
        p = np.pad(x, pad, mode="reflect")
        n = x.shape[axis]
        x = sum(t[i] * np.take(p, np.arange(i, i + n), axis=axis) for i in range(len(t)))
    return np.floor(x + 0.5).clip(0, 255).astype(np.uint8)


def smooth_colors(color: np.ndarray, sigma_px: float) -> np.ndarray:
    """:func:`smooth_colors_ref` by ``cv2.GaussianBlur`` (~1 ms at 640x480). New uint8 (H, W, 3)."""
    check_smooth_input(color, sigma_px)
    if sigma_px < MIN_SIGMA_PX:
        return color.copy()
    k = kernel_size(sigma_px)
    return cv2.GaussianBlur(color, (k, k), sigma_px, sigmaY=sigma_px, borderType=cv2.BORDER_REFLECT_101)
