"""Plain numpy reference of the synthesis kernels: the definitions the fast paths are tested against.

A point lands on pixel ``floor(u + 0.5)``; z <= ``near_m`` is dropped; per layer the smallest float32 z wins, ties to
the lower point index; empty = depth 0, colour 0; the switching median (eq. 3.9) fills an empty pixel whose N x N
window (outside = empty) is more than half non-empty with the lower median per channel; the plain median takes the
zero-padded window; layers composite front to back."""

from __future__ import annotations

import numpy as np

from presim.capture.reprojection import zbuffer_splat
from presim.geometry import Intrinsics, project, transform_points, unproject_depth
from presim.synthesis.warp import ViewPoints

__all__ = ["assign_layers_ref", "prepare_view_ref", "warp_layers_ref", "switching_median_ref", "plain_median_ref",
           "composite_layers_ref"]


def assign_layers_ref(depth_m: np.ndarray, num_layers: int) -> tuple[np.ndarray, tuple[float, float]]:
    """``(layer, (min, max))``: int64 (n,) layer of each valid depth (> 0, metres), ``num_layers`` equal slices
    of [min, max] (0 = nearest, max in the last)."""
    d = np.asarray(depth_m, dtype=np.float64)
    if num_layers < 1:
        raise ValueError(f"num_layers must be >= 1, got {num_layers}")
    if d.size == 0:
        return np.zeros(0, np.int64), (0.0, 0.0)
    lo, hi = float(d.min()), float(d.max())
    if hi <= lo:
        return np.zeros(d.shape, np.int64), (lo, hi)
    return np.minimum(((d - lo) / (hi - lo) * num_layers).astype(np.int64), num_layers - 1), (lo, hi)


def prepare_view_ref(color: np.ndarray, depth_m: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                     num_layers: int) -> ViewPoints:
    """Reference of :func:`presim.synthesis.warp.prepare_view` (numpy, via geometry.py), without ``image``."""
    if color.shape != (K.height, K.width, 3) or color.dtype != np.uint8:
        raise ValueError(f"color must be uint8 {K.height}x{K.width}x3, got {color.dtype} {color.shape}")
    pts, mask = unproject_depth(K, depth_m, T_world_cam)
    layer, rng = assign_layers_ref(np.asarray(depth_m)[mask], num_layers)
    order = np.argsort(layer, kind="stable")
    start = np.zeros(num_layers + 1, np.int64)
    start[1:] = np.cumsum(np.bincount(layer, minlength=num_layers))
    return ViewPoints(np.ascontiguousarray(pts[order], np.float32),
                      np.ascontiguousarray(color[mask][order], np.uint8), start, rng, T_world_cam)


def warp_layers_ref(xyz_world: np.ndarray, rgb: np.ndarray, layer: np.ndarray, num_layers: int,
                    T_cam_world: np.ndarray, K: Intrinsics, near_m: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Forward-warp world points (n, 3) with ``rgb`` and ``layer`` into ``num_layers`` z-buffered images of
    the target camera: ``(depth_m (L, H, W) float32, color (L, H, W, 3) uint8)``, 0 where empty."""
    H, W = K.height, K.width
    depth = np.zeros((num_layers, H, W), np.float32)
    color = np.zeros((num_layers, H, W, 3), np.uint8)
    p_cam = transform_points(T_cam_world, np.asarray(xyz_world, np.float64))
    uv, z = project(K, p_cam)
    rgb = np.asarray(rgb)
    layer = np.asarray(layer)
    for lay in range(num_layers):
        pts = np.flatnonzero(layer == lay)  # this layer's points, in point order
        lin, win = _splat_front(uv[pts], z[pts], near_m, W, H)
        depth[lay].reshape(-1)[lin] = z[pts[win]]
        color[lay].reshape(-1, 3)[lin] = rgb[pts[win]]
    return depth, color


def _splat_front(uv: np.ndarray, z: np.ndarray, near_m: float, W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`zbuffer_splat` of points with ``z > near_m`` (float32 depths) -> (flat pixel, winning index)."""
    front = np.flatnonzero(z > near_m)
    lin, win = zbuffer_splat(uv[front], z[front].astype(np.float32), W, H)
    return lin, front[win]


def _windows(a: np.ndarray, r: int) -> np.ndarray:
    """Each pixel's (2r + 1) x (2r + 1) window of ``a`` (H, W, ...), zero outside the image: (H, W, ..., n)."""
    w = np.lib.stride_tricks.sliding_window_view(np.pad(a, [(r, r), (r, r)] + [(0, 0)] * (a.ndim - 2)),
                                                 (2 * r + 1, 2 * r + 1), axis=(0, 1))
    return w.reshape(w.shape[:-2] + (-1,))


def switching_median_ref(depth_m: np.ndarray, color: np.ndarray, kernel_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Switching median (eq. 3.9) of one image: depth (H, W), color (H, W, 3). Returns new arrays."""
    r = kernel_px // 2
    full = _windows(depth_m, r) > 0  # (H, W, n): the window's non-empty pixels
    n = full.sum(-1)
    fill = ~(depth_m > 0) & (2 * n > kernel_px * kernel_px)
    k = ((n[fill] - 1) // 2)[:, None]  # the lower median of the non-empty values; empties sort last
    out_d, out_c = depth_m.copy(), color.copy()
    d = np.sort(np.where(full[fill], _windows(depth_m, r)[fill], np.float32(np.inf)), -1)
    c = np.sort(np.where(full[fill][:, None], _windows(color, r)[fill], np.uint8(255)), -1)  # (m, 3, n)
    out_d[fill] = np.take_along_axis(d, k, -1)[:, 0]
    out_c[fill] = np.take_along_axis(c, k[:, None], -1)[..., 0]
    return out_d, out_c


def plain_median_ref(depth_m: np.ndarray, color: np.ndarray, kernel_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Median of each pixel's N x N window (zero padded, empties included); colour 0 where median depth is not > 0."""
    r, mid = kernel_px // 2, (kernel_px * kernel_px - 1) // 2
    out_d = np.sort(_windows(depth_m, r), -1)[..., mid]
    out_c = np.where((out_d > 0)[..., None], np.sort(_windows(color, r), -1)[..., mid], np.uint8(0))
    return out_d, out_c


def composite_layers_ref(depth_m: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Composite of (L, H, W) / (L, H, W, 3) layers -> (H, W), (H, W, 3): each pixel's first non-empty layer, else 0."""
    full = depth_m > 0
    front = np.argmax(full, axis=0)[None]
    hit = full.any(0)
    out_d = np.where(hit, np.take_along_axis(depth_m, front, 0)[0], np.float32(0))
    out_c = np.where(hit[..., None], np.take_along_axis(color, front[..., None], 0)[0], np.uint8(0))
    return out_d, out_c
