"""The completion stage: pixels no measured depth covers take the warped views' completed depth.

After the adaptive loop, the points of each warped view's completed depth (:mod:`presim.depth.complete`)
are splatted with a z-buffer into the pixels still empty, and one-pixel cracks between them (a hole
pixel empty with at least 5 of its 8 neighbours hit) take the nearest hit neighbour. Only empty pixels
are written, so measured depth always wins. Numba kernel :func:`splat_into_holes`, numpy reference
:func:`splat_into_holes_ref` (tested equal), torch :func:`presim.synthesis.torch_kernels.splat_into_holes_torch`."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from presim.geometry import Intrinsics

__all__ = ["CompletedPoints", "splat_into_holes", "splat_into_holes_ref"]


class CompletedPoints(NamedTuple):
    """One view's completed points."""

    view_id: int
    xyz_world: np.ndarray
    """float32 (n, 3)."""
    rgb: np.ndarray
    """uint8 (n, 3)."""


class Target(NamedTuple):
    """The frame's accumulated image, written in place on the hole pixels."""

    depth_m: np.ndarray
    color: np.ndarray
    source: np.ndarray
    holes: np.ndarray
    """uint8 (H, W), non-zero = empty; cleared where a completed point lands."""


def _project(xyz: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics, near_m: float):
    M = np.asarray(T_cam_world, np.float64)
    X, Y, Z = (xyz[:, k].astype(np.float64) for k in range(3))
    x, y, z = (M[r, 0] * X + M[r, 1] * Y + M[r, 2] * Z + M[r, 3] for r in range(3))  # the kernel's order
    ok = z > near_m
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(K.fx * x / z + K.cx + 0.5)
        v = np.floor(K.fy * y / z + K.cy + 0.5)
    ok &= (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    return u, v, z, ok


_NB8 = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def splat_into_holes_ref(points: list[CompletedPoints], T_cam_world: np.ndarray, K: Intrinsics, near_m: float,
                         target: Target) -> int:
    """Reference of :func:`splat_into_holes` (numpy)."""
    H, W = K.height, K.width
    zbuf = np.zeros((H, W), np.float64)
    cbuf = np.zeros((H, W, 3), np.uint8)
    sbuf = np.full((H, W), -1, np.int32)
    for cp in points:  # in view order: a later view wins only when strictly nearer
        u, v, z, ok = _project(cp.xyz_world, T_cam_world, K, near_m)
        for i in np.flatnonzero(ok):
            y, x = int(v[i]), int(u[i])
            if target.holes[y, x] and (zbuf[y, x] == 0 or z[i] < zbuf[y, x]):
                zbuf[y, x], cbuf[y, x], sbuf[y, x] = z[i], cp.rgb[i], cp.view_id
    hit = zbuf > 0
    add = []
    for y, x in zip(*np.nonzero((target.holes != 0) & ~hit)):
        nbrs = [(zbuf[y + dy, x + dx], y + dy, x + dx) for dy, dx in _NB8
                if 0 <= y + dy < H and 0 <= x + dx < W and hit[y + dy, x + dx]]
        if len(nbrs) >= 5:
            add.append((y, x, min(nbrs)))
    for y, x, (zz, yy, xx) in add:
        zbuf[y, x], cbuf[y, x], sbuf[y, x] = zz, cbuf[yy, xx], sbuf[yy, xx]
    filled = zbuf > 0
    target.depth_m[filled] = zbuf[filled].astype(np.float32)
    target.color[filled] = cbuf[filled]
    target.source[filled] = sbuf[filled]
    target.holes[filled] = 0
    return int(filled.sum())


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _splat_kernel(xyz, rgb, view_id, M, cam, holes, zbuf, cbuf, sbuf):  # pragma: no cover
    fx, fy, cx, cy, near = cam[0], cam[1], cam[2], cam[3], cam[4]
    H, W = holes.shape
    for i in range(xyz.shape[0]):
        X = float(xyz[i, 0])
        Y = float(xyz[i, 1])
        Z = float(xyz[i, 2])
        z = M[2, 0] * X + M[2, 1] * Y + M[2, 2] * Z + M[2, 3]
        if not z > near:
            continue
        x = M[0, 0] * X + M[0, 1] * Y + M[0, 2] * Z + M[0, 3]
        y = M[1, 0] * X + M[1, 1] * Y + M[1, 2] * Z + M[1, 3]
        uf = np.floor(fx * x / z + cx + 0.5)
        vf = np.floor(fy * y / z + cy + 0.5)
        if not (uf >= 0 and uf < W and vf >= 0 and vf < H):
            continue
        u = int(uf)
        v = int(vf)
        if holes[v, u] != 0 and (zbuf[v, u] == 0 or z < zbuf[v, u]):
            zbuf[v, u] = z
            cbuf[v, u, 0] = rgb[i, 0]
            cbuf[v, u, 1] = rgb[i, 1]
            cbuf[v, u, 2] = rgb[i, 2]
            sbuf[v, u] = view_id


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _close_kernel(holes, zbuf, cbuf, sbuf, depth, color, source):  # pragma: no cover
    # cracks: empty hole pixels with >= 5 hit neighbours take the nearest one (decided on the splat alone),
    # then every hit pixel goes into the image
    H, W = holes.shape
    add_y = np.empty(H * W, np.int32)
    add_x = np.empty(H * W, np.int32)
    src_y = np.empty(H * W, np.int32)
    src_x = np.empty(H * W, np.int32)
    n_add = 0
    for y in range(H):
        for x in range(W):
            if holes[y, x] == 0 or zbuf[y, x] > 0:
                continue
            cnt = 0
            best = np.inf
            by = bx = -1
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = y + dy
                    xx = x + dx
                    if (dy == 0 and dx == 0) or yy < 0 or yy >= H or xx < 0 or xx >= W or zbuf[yy, xx] == 0:
                        continue
                    cnt += 1
                    if zbuf[yy, xx] < best:
                        best = zbuf[yy, xx]
                        by = yy
                        bx = xx
            if cnt >= 5:
                add_y[n_add] = y
                add_x[n_add] = x
                src_y[n_add] = by
                src_x[n_add] = bx
                n_add += 1
    for k in range(n_add):
        y, x, yy, xx = add_y[k], add_x[k], src_y[k], src_x[k]
        zbuf[y, x] = zbuf[yy, xx]
        for c in range(3):
            cbuf[y, x, c] = cbuf[yy, xx, c]
        sbuf[y, x] = sbuf[yy, xx]
    n = 0
    for y in range(H):
        for x in range(W):
            if zbuf[y, x] > 0:
                depth[y, x] = np.float32(zbuf[y, x])
                for c in range(3):
                    color[y, x, c] = cbuf[y, x, c]
                source[y, x] = sbuf[y, x]
                holes[y, x] = 0
                n += 1
    return n


def splat_into_holes(points: list[CompletedPoints], T_cam_world: np.ndarray, K: Intrinsics, near_m: float,
                     target: Target) -> int:
    """Splat into the holes of ``target`` (module docstring); returns the pixels filled (``target.holes`` cleared)."""
    H, W = K.height, K.width
    zbuf = np.zeros((H, W), np.float64)
    cbuf = np.zeros((H, W, 3), np.uint8)
    sbuf = np.full((H, W), -1, np.int32)
    M = np.ascontiguousarray(T_cam_world, np.float64)
    cam = np.array([K.fx, K.fy, K.cx, K.cy, near_m], np.float64)
    for cp in points:
        _splat_kernel(cp.xyz_world, cp.rgb, np.int32(cp.view_id), M, cam, target.holes, zbuf, cbuf, sbuf)
    return int(_close_kernel(target.holes, zbuf, cbuf, sbuf, target.depth_m, target.color, target.source))
