"""Seeded depth noise: axial noise growing with distance and dropouts (holes), like a real sensor.

Axial noise follows the structured-light model of Nguyen, Izadi & Lovell (3DIMPVT 2012):
``sigma_z(z) = a + b * (z - z0)^2`` (defaults: a = 1.2 mm, b = 1.9 mm/m^2, z0 = 0.4 m). Dropouts:
every pixel is lost with ``dropout_prob``, plus everything nearer than ``min_range_m`` or farther
than ``max_range_m``. All randomness comes from the generator the caller passes (seeded by the
simulator), so a seed reproduces the noise exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DepthNoiseConfig", "depth_noise_sigma_m", "apply_depth_noise"]


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Depth noise model parameters."""

    sigma_base_m: float = 0.0012
    """Axial standard deviation at ``sigma_ref_m``, metres."""
    sigma_quad_m: float = 0.0019
    """Growth of the standard deviation with squared distance beyond ``sigma_ref_m``, m per m^2."""
    sigma_ref_m: float = 0.4
    """Distance of the minimum noise, metres."""
    dropout_prob: float = 0.01
    """Probability that a valid pixel reads 0 (random dropouts)."""
    min_range_m: float = 0.3
    """Depth below this reads 0 (too close for the sensor)."""
    max_range_m: float = 8.0
    """Depth above this reads 0 (out of range)."""
    quantize_m: float = 0.001
    """Output quantization step (1 mm like 16-bit mm PNGs); 0 = none."""


def depth_noise_sigma_m(depth_m: np.ndarray, cfg: DepthNoiseConfig) -> np.ndarray:
    """Axial noise standard deviation (metres) at each depth (metres)."""
    z = np.asarray(depth_m, dtype=np.float32)
    return (cfg.sigma_base_m + cfg.sigma_quad_m * np.square(np.maximum(z - cfg.sigma_ref_m, 0.0))).astype(np.float32)


def apply_depth_noise(depth_m: np.ndarray, rng: np.random.Generator, cfg: DepthNoiseConfig) -> np.ndarray:
    """Noisy copy of ``depth_m`` (float32 (H, W) metres, 0 = invalid); invalid stays 0.

    Example:
        >>> d = np.full((4, 4), 2.0, np.float32)
        >>> out = apply_depth_noise(d, np.random.default_rng(0), DepthNoiseConfig(dropout_prob=0))
        >>> bool(np.all(np.abs(out - 2.0) < 0.05))
        True
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2 or depth_m.dtype != np.float32:
        raise ValueError(f"depth must be float32 (H, W), got {depth_m.dtype} {depth_m.shape}")
    noise = rng.standard_normal(depth_m.shape, dtype=np.float32)
    drop = rng.random(depth_m.shape, dtype=np.float32) < cfg.dropout_prob
    out = depth_m + noise * depth_noise_sigma_m(depth_m, cfg)
    if cfg.quantize_m > 0:
        out = np.round(out / cfg.quantize_m) * cfg.quantize_m
    keep = (depth_m > 0) & ~drop & (depth_m >= cfg.min_range_m) & (depth_m <= cfg.max_range_m) & (out > 0)
    return np.where(keep, out, 0.0).astype(np.float32)
