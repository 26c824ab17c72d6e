"""The sample scene's depth sensor: a realistically corrupted copy of the exact depth.

The axial noise law itself lives in :mod:`presim.sensors.noise` (:class:`QuadraticNoiseConfig`);
this module adds what a structured-light camera does around it: edge effects, holes, range limits
and color/depth misregistration.
"""

from __future__ import annotations

import numpy as np

from presim.capture.sample_scene.config import SampleSceneConfig
from presim.sensors.noise import add_quadratic_noise

__all__ = ["corrupt_depth"]


def corrupt_depth(depth_m: np.ndarray, albedo_lum: np.ndarray, cos_incidence: np.ndarray,
                  config: SampleSceneConfig, rng: np.random.Generator) -> np.ndarray:
    """A realistic sensor reading of the exact depth ``depth_m`` (float32 (H, W), 0 = none).

    In this order: foreground dilation at depth edges (``edge_dilate_px``), holes left of nearer
    surfaces (projector shadow, ``edge_shadow_px``), on dark surfaces (``dark_albedo``,
    ``dark_dropout``), at grazing incidence (``grazing_deg``) and random speckles; Gaussian noise with
    ``sigma = noise_sigma0_m + noise_k_per_m * z^2`` (:func:`presim.sensors.noise.add_quadratic_noise`); no depth outside ``[min_range_m, max_range_m]``;
    finally the whole map is shifted by
    ``shift_px`` relative to the color (registration error), vacated borders are 0.
    """
    import cv2

    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim != 2 or albedo_lum.shape != d.shape or cos_incidence.shape != d.shape:
        raise ValueError(f"depth, albedo and incidence must be (H, W) of one shape, got "
                         f"{d.shape}, {albedo_lum.shape}, {cos_incidence.shape}")
    valid = d > 0
    big = np.where(valid, d, np.float32(1e3))
    kernel = np.ones((3, 3), np.uint8)
    dmin = cv2.erode(big, kernel)
    # A depth edge: a 3x3 neighbour is closer by more than 4 % of the depth (or 5 cm).
    far_side = valid & (big - dmin > np.maximum(0.04 * big, 0.05))
    out = d.copy()
    if config.edge_dilate_px > 0:
        k = np.ones((2 * config.edge_dilate_px + 1,) * 2, np.uint8)
        grown = cv2.erode(big, k)
        band = cv2.dilate(far_side.astype(np.uint8), k).astype(bool) & valid
        take = band & (grown < big - np.maximum(0.04 * big, 0.05))
        out[take] = grown[take]
    drop = np.zeros(d.shape, bool)
    if config.edge_shadow_px > 0:
        # The IR projector sits to the right of the camera: background up to edge_shadow_px pixels to
        # the LEFT of a nearer surface is not lit by the pattern (one-sided holes, like a Kinect).
        W = config.edge_shadow_px
        right_min = cv2.erode(big, np.ones((1, W + 1), np.uint8), anchor=(0, 0),
                              borderType=cv2.BORDER_CONSTANT, borderValue=1e3)
        shadow = valid & (d - right_min > np.maximum(0.04 * d, 0.05))
        drop |= shadow & (rng.random(d.shape) < 0.8)
    drop |= (albedo_lum < config.dark_albedo) & (rng.random(d.shape) < config.dark_dropout)
    ang = np.degrees(np.arccos(np.clip(cos_incidence, 0, 1)))
    p_graze = np.clip((ang - (config.grazing_deg - 6.0)) / 12.0, 0, 1)
    drop |= rng.random(d.shape) < p_graze
    drop |= rng.random(d.shape) < config.speckle_dropout
    out = add_quadratic_noise(out, rng, config.depth_noise)
    drop |= (out < config.min_range_m) | (out > config.max_range_m)
    out[drop | ~(out > 0)] = 0.0
    du, dv = config.shift_px
    shifted = np.zeros_like(out)
    h, w = out.shape
    shifted[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = \
        out[max(-dv, 0):h + min(-dv, 0), max(-du, 0):w + min(-du, 0)]
    return shifted.astype(np.float32)
