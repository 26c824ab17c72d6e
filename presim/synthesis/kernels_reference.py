"""Plain numpy reference of the synthesis kernels: the definitions the fast paths are tested against.

A point lands on pixel ``floor(u + 0.5)``; z <= ``near_m`` is dropped; per layer the smallest float32 z wins, ties to
the lower point index; empty = depth 0, colour 0; the switching median (eq. 3.9) fills an empty pixel whose N x N
window (outside = empty) is more than half non-empty with the lower median per channel; the plain median takes the
zero-padded window; layers composite front to back."""

from __future__ import annotations

import numpy as np

from presim.capture.reprojection import zbuffer_splat
from presim.geometry import Intrinsics, project, transform_points

__all__ = ["assign_layers_ref", "warp_layers_ref", "switching_median_ref", "plain_median_ref", "composite_layers_ref"]


def assign_layers_ref(depth_m: np.ndarray, num_layers: int) -> np.ndarray:
    """int64 (n,) layer of each ``depth_m`` (all > 0): ``num_layers`` equal slices of [min, max], layer 0 nearest."""
    d = np.asarray(depth_m, dtype=np.float64)
    if d.size == 0:
        return np.zeros(0, np.int64)
    lo, hi = d.min(), d.max()
    if hi <= lo:
        return np.zeros(d.shape, np.int64)
    out = np.empty(d.shape, np.int64)
    for i, di in enumerate(d):
        out[i] = min(int((di - lo) / (hi - lo) * num_layers), num_layers - 1)
    return out


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


def tile_any_ref(mask: np.ndarray, tile_h: int, tile_w: int, grow: int) -> np.ndarray:
    """Reference of :func:`presim.synthesis.cracks.tile_any`: uint8 (ceil(H / tile_h), ceil(W / tile_w)), 1 where
    a nonzero ``mask`` pixel lies within ``grow`` pixels (Chebyshev) of the tile."""
    m = np.asarray(mask) != 0
    H, W = m.shape
    grown = np.zeros_like(m)
    for dy in range(-grow, grow + 1):
        for dx in range(-grow, grow + 1):
            src = m[max(-dy, 0):H - max(dy, 0), max(-dx, 0):W - max(dx, 0)]
            grown[max(dy, 0):H - max(-dy, 0), max(dx, 0):W - max(-dx, 0)] |= src
    th, tw = -(-H // tile_h), -(-W // tile_w)
    padded = np.zeros((th * tile_h, tw * tile_w), bool)
    padded[:H, :W] = grown
    return padded.reshape(th, tile_h, tw, tile_w).any(axis=(1, 3)).astype(np.uint8)
