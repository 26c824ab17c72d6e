"""Level of detail: a pyramid of point sets per capture view, one level per frame.

Level k+1 is 2x2 depth-aware pooling of level k (:func:`presim.imaging.pool.pool_depth_aware`: a block's pixels
within ``depth_tol`` of its nearest depth are averaged, the rest ignored). :func:`choose_level` takes the coarsest
level whose median footprint ``2^k (z_s / f_s) / (z_t / f_t)`` is <= ``max_footprint``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.capture.reprojection import nearest_pixel
from presim.geometry import Intrinsics, project, transform_points
from presim.imaging.pool import pool_depth_aware

__all__ = ["LodConfig", "half_intrinsics", "build_level", "footprint_ratio", "choose_level"]


@dataclass(frozen=True)
class LodConfig:
    """Level-of-detail knobs (``RenderConfig.lod_levels``, ``lod_max_footprint``, ``lod_depth_tol``)."""

    levels: int = 3
    """Coarsest level (0 = no level of detail: always the full view)."""
    max_footprint: float = 1.0
    """A level is usable while one of its points covers at most this many target pixels (median)."""
    depth_tol: float = 0.02
    """Relative depth band of the front surface in a 2x2 block (pooled together)."""


def half_intrinsics(K: Intrinsics) -> Intrinsics:
    """Intrinsics of a 2x2-pooled image (``W // 2`` x ``H // 2``; block i = source pixels 2i..2i+1, centre 2i + 0.5)."""
    return Intrinsics(K.fx / 2.0, K.fy / 2.0, (K.cx - 0.5) / 2.0, (K.cy - 0.5) / 2.0, K.width // 2, K.height // 2)


def build_level(color: np.ndarray, depth_m: np.ndarray, K: Intrinsics, level: int, depth_tol: float = 0.02
                ) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """Pyramid level ``level`` (0 = input) as ``(color, depth, intrinsics)``."""
    for _ in range(level):
        if min(depth_m.shape) < 2:
            break
        depth_m, color = pool_depth_aware(depth_m, color, depth_tol)
        K = half_intrinsics(K)
    return color, depth_m, K


def footprint_ratio(grid_xyz_world: np.ndarray, T_cam_world_src: np.ndarray, f_src_px: float,
                    T_cam_world_tgt: np.ndarray, f_tgt_px: float, near_m: float = 0.01,
                    K_tgt: Intrinsics | None = None) -> float:
    """Median over a view's grid points in front of both cameras (and inside ``K_tgt`` when given) of
    ``(z_s / f_s) / (z_t / f_t)``; nan when none counts."""
    if len(grid_xyz_world) == 0:
        return float("nan")
    z_s = transform_points(T_cam_world_src, grid_xyz_world)[:, 2]
    p_t = transform_points(T_cam_world_tgt, grid_xyz_world)
    z_t = p_t[:, 2]
    ok = (z_s > near_m) & (z_t > near_m)
    if K_tgt is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            uv, _ = project(K_tgt, p_t)
        ok &= nearest_pixel(uv, K_tgt.width, K_tgt.height)[2]
    if not ok.any():
        return float("nan")
    return float(np.median(z_s[ok] / z_t[ok]) * f_tgt_px / f_src_px)


def choose_level(ratio0: float, config: LodConfig) -> int:
    """Coarsest k <= ``config.levels`` with ``2^k * ratio0 <= config.max_footprint`` (0 if ratio0 not finite)."""
    if not np.isfinite(ratio0) or ratio0 <= 0:
        return 0
    k = 0
    while k < config.levels and (2 ** (k + 1)) * ratio0 <= config.max_footprint:
        k += 1
    return k
