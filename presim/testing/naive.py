"""The naive baseline of view synthesis (benchmarks, tests): a numpy z-buffer splat of whole frames."""

from __future__ import annotations

import numpy as np

from presim.capture.reprojection import zbuffer_splat
from presim.geometry import Intrinsics, compose, invert, project, unproject_depth


def naive_zbuffer(views: list[tuple[np.ndarray, np.ndarray, Intrinsics, np.ndarray]], T_world_cam: np.ndarray,
                  K: Intrinsics, near_m: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Splat whole frames ``(color, depth_m, K_view, T_world_view)`` into the target camera with one z-buffer:
    no layers, no filters, nothing cached. Returns ``(color (H, W, 3), depth_m (H, W))``, 0 where empty."""
    H, W = K.height, K.width
    zbuf = np.full(H * W, np.inf, np.float32)
    out = np.zeros((H * W, 3), np.uint8)
    T_cam_world = invert(T_world_cam)
    for color_v, depth_v, K_v, T_world_v in views:
        pts, mask = unproject_depth(K_v, depth_v, compose(T_cam_world, T_world_v))
        uv, z = project(K, pts)
        front = np.flatnonzero(z > near_m)
        lin, win = zbuffer_splat(uv[front], z[front].astype(np.float32), W, H)
        zz, cc = z[front[win]].astype(np.float32), color_v[mask][front[win]]
        closer = zz < zbuf[lin]
        zbuf[lin[closer]] = zz[closer]
        out[lin[closer]] = cc[closer]
    depth = np.where(np.isfinite(zbuf), zbuf, 0).astype(np.float32)
    return out.reshape(H, W, 3), depth.reshape(H, W)
