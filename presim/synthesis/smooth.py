"""Reconstruction filter of the output colour: a Gaussian of ``sigma`` output pixels.

A splat carries the colour of one source pixel, placed up to half a pixel off, and that pixel's sensor
noise; the real camera's image of the same pose has its own noise and the views sit a fraction of a pixel
off it. A small Gaussian weighs these errors against detail. Its width is fitted per capture by
leave-one-out renders of capture frames (:mod:`presim.evaluation.smooth_fit`, ``SCENE/render_filter.json``);
a scene without a fit is not filtered.

Reference :func:`smooth_colors_ref` (float64, reflected border, rounding half up); fast path
:func:`smooth_colors` (OpenCV's fixed-point Gaussian, within one grey level of the reference); torch
:func:`smooth_colors_torch`."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MIN_SIGMA_PX", "kernel_size", "gaussian_taps", "smooth_colors_ref", "smooth_colors",
           "smooth_colors_torch"]

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


def _check(color: np.ndarray, sigma_px: float) -> None:
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"smooth: need uint8 (H, W, 3) colour, got {color.dtype} {color.shape}")
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"smooth: sigma must be a finite number >= 0, got {sigma_px}")


def smooth_colors_ref(color: np.ndarray, sigma_px: float) -> np.ndarray:
    """Separable Gaussian (rows, then columns) in float64 with the border reflected (``dcb|abcd|cba``),
    ``floor(x + 0.5)``. New uint8 (H, W, 3); a copy below :data:`MIN_SIGMA_PX`."""
    _check(color, sigma_px)
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
    _check(color, sigma_px)
    if sigma_px < MIN_SIGMA_PX:
        return color.copy()
    k = kernel_size(sigma_px)
    return cv2.GaussianBlur(color, (k, k), sigma_px, sigmaY=sigma_px, borderType=cv2.BORDER_REFLECT_101)


def smooth_colors_torch(color: np.ndarray, sigma_px: float, device=None) -> np.ndarray:
    """:func:`smooth_colors_ref` as two float32 1-D convolutions in torch (CUDA when present), within one
    grey level of the reference. New uint8 (H, W, 3)."""
    import torch  # only on the torch backend

    from presim.synthesis.torch_kernels import resolve_device

    _check(color, sigma_px)
    if sigma_px < MIN_SIGMA_PX:
        return color.copy()
    dev = resolve_device(device)
    t = torch.as_tensor(gaussian_taps(sigma_px), dtype=torch.float32, device=dev)
    r = len(t) // 2
    x = torch.from_numpy(np.ascontiguousarray(color)).to(dev).permute(2, 0, 1)[:, None].float()  # (3, 1, H, W)
    f = torch.nn.functional
    x = f.conv2d(f.pad(x, (r, r, 0, 0), mode="reflect"), t.view(1, 1, 1, -1))
    x = f.conv2d(f.pad(x, (0, 0, r, r), mode="reflect"), t.view(1, 1, -1, 1))
    out = torch.floor(x[:, 0] + 0.5).clamp(0, 255).to(torch.uint8).permute(1, 2, 0)
    return out.cpu().numpy()
