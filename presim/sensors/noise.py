"""Seeded depth noise laws: axial noise growing with distance, like a real structured-light sensor.

Two laws, one config dataclass each (docs/simulator.md, "Sensor noise"):

- :class:`DepthNoiseConfig` / :func:`apply_depth_noise` -- the simulated RGB-D camera. Axial noise
  follows Nguyen, Izadi & Lovell (3DIMPVT 2012): ``sigma_z(z) = a + b * (z - z0)^2`` (defaults:
  a = 1.2 mm, b = 1.9 mm/m^2, z0 = 0.4 m), then quantization; dropouts: every pixel is lost with
  ``dropout_prob``, plus everything nearer than ``min_range_m`` or farther than ``max_range_m``.
- :class:`QuadraticNoiseConfig` / :func:`add_quadratic_noise` -- the sample scene's sensor
  (:func:`presim.capture.sample_scene.corrupt_depth`): ``sigma(z) = sigma0 + k * z^2`` (defaults:
  0.5 mm + 1.5 mm/m^2 * z^2), Gaussian noise only; its holes, edge effects and range limits are
  applied by the caller. It stays a separate law (not ``DepthNoiseConfig`` with z0 = 0) because it
  draws float64 normals and evaluates ``sigma`` in a different order: sample scenes built from a seed
  stay byte-identical.

All randomness comes from the generator the caller passes, so a seed reproduces the noise exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "DepthNoiseConfig", "depth_noise_sigma_m", "apply_depth_noise",
    "QuadraticNoiseConfig", "quadratic_noise_sigma_m", "add_quadratic_noise",
]


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


@dataclass(frozen=True)
class QuadraticNoiseConfig:
    """Axial noise ``sigma(z) = sigma0_m + k_per_m * z^2`` (the sample scene's structured-light sensor)."""

    sigma0_m: float = 0.0005
    """Standard deviation at z = 0, metres."""
    k_per_m: float = 0.0015
    """Growth of the standard deviation with squared depth, m per m^2 (1/m)."""


def quadratic_noise_sigma_m(depth_m: np.ndarray, cfg: QuadraticNoiseConfig) -> np.ndarray:
    """Axial noise standard deviation (metres) at each float32 depth (metres): ``sigma0 + k * z^2``.

    Example (hand-computed: 0.5 mm + 1.5 mm/m^2 * (2 m)^2 = 6.5 mm):
        >>> float(quadratic_noise_sigma_m(np.float32([2.0]), QuadraticNoiseConfig())[0])  # doctest: +ELLIPSIS
        0.0065...
    """
    z = np.asarray(depth_m, dtype=np.float32)
    return cfg.sigma0_m + cfg.k_per_m * z * z


def add_quadratic_noise(depth_m: np.ndarray, rng: np.random.Generator, cfg: QuadraticNoiseConfig) -> np.ndarray:
    """``depth_m + N(0, 1) * quadratic_noise_sigma_m(depth_m)``, float32, same shape.

    Draws one float64 standard normal per pixel from ``rng`` (cast to float32). Pixels with depth 0
    get noise of ``sigma0_m``: masking invalid pixels and range limits is left to the caller.
    """
    z = np.asarray(depth_m, dtype=np.float32)
    noise = rng.standard_normal(z.shape).astype(np.float32)
    return z + noise * quadratic_noise_sigma_m(z, cfg)
