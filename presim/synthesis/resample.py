"""Backward colour sampling: each rendered pixel's colour read from its source view's image.

A one-pixel splat carries the colour of the nearest source pixel (up to half a pixel off). Here the target pixel
is back-projected with its depth into its source view and its colour interpolated bilinearly there; taps whose
source depth disagrees by more than ``depth_tol`` (relative) are dropped, and a pixel with no valid tap keeps its
colour. Reference :func:`resample_colors_ref`; numba :func:`resample_colors`; torch ``resample_colors_torch``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numba as nb
import numpy as np

from presim.geometry import Intrinsics
from presim.numba_threads import parallel_kernel

__all__ = ["MAX_SOURCES", "SourceImage", "SourceStack", "stack_sources", "source_projection", "resample_colors_ref",
           "resample_colors"]


@dataclass(frozen=True)
class SourceImage:
    """One view's image as its points were prepared from (the level of detail's pooled image)."""

    color: np.ndarray
    """uint8 (h, w, 3), photometrically corrected like the points."""
    depth_m: np.ndarray
    """float32 (h, w), 0 = invalid."""
    K: Intrinsics
    T_cam_world: np.ndarray
    """4x4 world -> this view's camera."""

    @property
    def nbytes(self) -> int:
        return int(self.color.nbytes + self.depth_m.nbytes)


MAX_SOURCES = 16
"""Views a frame's resampling reads at most (fixed-size tuples: one compilation); pixels of further
views keep their splatted colour."""


class SourceStack(NamedTuple):
    """A frame's source images for the kernels (tuples padded to :data:`MAX_SOURCES` entries)."""

    lut: np.ndarray
    """int32 (max_id + 1,): view id -> its index in the tuples, -1 = not given."""
    colors: tuple
    """uint8 (h, w, 3) per view."""
    depths: tuple
    """float32 (h, w) per view."""
    intr: np.ndarray
    """float64 (MAX_SOURCES, 4): fx, fy, cx, cy."""
    T: np.ndarray
    """float64 (MAX_SOURCES, 3, 4): world -> view camera."""


def stack_sources(ids: Sequence[int], images: Sequence[SourceImage]) -> SourceStack:
    """The first :data:`MAX_SOURCES` ``ids`` (scene frame indices) and ``images`` for the kernels (no pixel copy)."""
    ids, images = list(ids)[:MAX_SOURCES], list(images)[:MAX_SOURCES]
    n = len(ids)
    lut = np.full(max(ids, default=-1) + 1, -1, np.int32)
    for j, v in enumerate(ids):
        lut[v] = j
    pad = images + [images[0]] * (MAX_SOURCES - n) if n else []
    intr = np.zeros((MAX_SOURCES, 4))
    T = np.zeros((MAX_SOURCES, 3, 4))
    for j, im in enumerate(images):
        intr[j] = (im.K.fx, im.K.fy, im.K.cx, im.K.cy)
        T[j] = np.asarray(im.T_cam_world, np.float64)[:3]
    colors = tuple(np.ascontiguousarray(im.color, np.uint8) for im in pad)
    depths = tuple(np.ascontiguousarray(im.depth_m, np.float32) for im in pad)
    return SourceStack(lut, colors, depths, intr, T)


def _check(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics) -> None:
    H, W = K.height, K.width
    if color.shape != (H, W, 3) or depth_m.shape != (H, W) or source.shape != (H, W):
        raise ValueError(f"resample: need color (H, W, 3), depth (H, W), source (H, W) of {H}x{W}, got "
                         f"{color.shape}, {depth_m.shape}, {source.shape}")


def source_projection(K: Intrinsics, T_world_cam: np.ndarray, sources: SourceStack, j: int) -> np.ndarray:
    """float64 (3, 4): target camera point -> source view ``j``'s homogeneous pixel ``(u z, v z, z)``
    (``K_s T_src_world T_world_cam``), one matrix per view and frame."""
    fx, fy, cx, cy = sources.intr[j]
    Ks = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    T_wc = np.asarray(T_world_cam, np.float64)
    return Ks @ (sources.T[j][:, :3] @ T_wc[:3]) + Ks @ np.concatenate([np.zeros((3, 3)), sources.T[j][:, 3:]], 1)


def resample_colors_ref(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics,
                        T_world_cam: np.ndarray, sources: SourceStack, depth_tol: float = 0.05) -> np.ndarray:
    """Reference (float64). A pixel keeps ``color`` unless its source is in ``sources``, its depth > 0 and
    its projection lands in front of the source camera inside ``[0, w - 1] x [0, h - 1]`` with a tap within
    ``depth_tol``; then ``floor(sum(w c) / sum(w) + 0.5)`` over the valid bilinear taps. New uint8 (H, W, 3)."""
    _check(color, depth_m, source, K)
    out = color.copy()
    s = source.astype(np.int64)
    j_of = np.full(s.shape, -1, np.int64)
    ok = (s >= 0) & (s < len(sources.lut)) & (depth_m > 0)
    j_of[ok] = sources.lut[s[ok]]
    for j in np.unique(j_of[j_of >= 0]):
        P = source_projection(K, T_world_cam, sources, j)
        rows, cols = np.nonzero(j_of == j)
        d = depth_m[rows, cols].astype(np.float64)
        x, y = (cols - K.cx) / K.fx * d, (rows - K.cy) / K.fy * d
        p0 = P[0, 0] * x + P[0, 1] * y + P[0, 2] * d + P[0, 3]
        p1 = P[1, 0] * x + P[1, 1] * y + P[1, 2] * d + P[1, 3]
        zs = P[2, 0] * x + P[2, 1] * y + P[2, 2] * d + P[2, 3]
        img, dep = sources.colors[j], sources.depths[j]
        hs, ws = dep.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            us, vs = p0 / zs, p1 / zs
        inside = (zs > 0) & (us >= 0) & (us <= ws - 1) & (vs >= 0) & (vs <= hs - 1)
        us, vs, zs = us[inside], vs[inside], zs[inside]
        u0, v0 = np.floor(us).astype(np.int64), np.floor(vs).astype(np.int64)
        a, b = us - u0, vs - v0
        u1, v1 = np.minimum(u0 + 1, ws - 1), np.minimum(v0 + 1, hs - 1)
        acc = np.zeros((len(us), 3))
        wsum = np.zeros(len(us))
        lim = depth_tol * zs
        for uu, vv, w in ((u0, v0, (1 - a) * (1 - b)), (u1, v0, a * (1 - b)), (u0, v1, (1 - a) * b), (u1, v1, a * b)):
            ds = dep[vv, uu].astype(np.float64)
            w = np.where((ds > 0) & (np.abs(ds - zs) <= lim), w, 0.0)
            acc += w[:, None] * img[vv, uu].astype(np.float64)
            wsum += w
        use = wsum > 1e-9
        inv = 1.0 / wsum[use]
        out[rows[inside][use], cols[inside][use]] = (
            np.floor(acc[use] * inv[:, None] + 0.5).clip(0, 255).astype(np.uint8))
    return out


class _Target(NamedTuple):
    fx: float
    fy: float
    cx: float
    cy: float


@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _tap(img, dep, uu, vv, w, zs, lim, acc):  # pragma: no cover
    ds = np.float64(dep[vv, uu])
    if ds > 0.0 and abs(ds - zs) <= lim:
        acc[0] += w * img[vv, uu, 0]
        acc[1] += w * img[vv, uu, 1]
        acc[2] += w * img[vv, uu, 2]
        acc[3] += w


@parallel_kernel(cache=True, error_model="numpy")
def _resample_view_kernel(depth, source, view_id, tg, img, dep, P, tol, out):  # pragma: no cover
    # resample_colors_ref on the pixels of one source view (same float64 formulas, taps in order).
    H, W = depth.shape
    hs, ws = dep.shape
    wmax = np.float64(ws - 1)
    hmax = np.float64(hs - 1)
    for v in nb.prange(H):
        acc = np.empty(4)
        yn = (v - tg.cy) / tg.fy
        for u in range(W):
            d = np.float64(depth[v, u])
            if source[v, u] != view_id or not d > 0.0:
                continue
            x = (u - tg.cx) / tg.fx * d
            y = yn * d
            p0 = P[0, 0] * x + P[0, 1] * y + P[0, 2] * d + P[0, 3]
            p1 = P[1, 0] * x + P[1, 1] * y + P[1, 2] * d + P[1, 3]
            zs = P[2, 0] * x + P[2, 1] * y + P[2, 2] * d + P[2, 3]
            if not zs > 0.0:
                continue
            us = p0 / zs
            vs = p1 / zs
            if not (us >= 0.0 and us <= wmax and vs >= 0.0 and vs <= hmax):
                continue
            u0 = np.int64(np.floor(us))
            v0 = np.int64(np.floor(vs))
            a = us - u0
            b = vs - v0
            u1 = min(u0 + 1, ws - 1)
            v1 = min(v0 + 1, hs - 1)
            lim = tol * zs
            acc[:] = 0.0
            _tap(img, dep, u0, v0, (1 - a) * (1 - b), zs, lim, acc)
            _tap(img, dep, u1, v0, a * (1 - b), zs, lim, acc)
            _tap(img, dep, u0, v1, (1 - a) * b, zs, lim, acc)
            _tap(img, dep, u1, v1, a * b, zs, lim, acc)
            if acc[3] > 1e-9:
                inv = 1.0 / acc[3]
                out[v, u, 0] = np.uint8(min(255.0, max(0.0, np.floor(acc[0] * inv + 0.5))))
                out[v, u, 1] = np.uint8(min(255.0, max(0.0, np.floor(acc[1] * inv + 0.5))))
                out[v, u, 2] = np.uint8(min(255.0, max(0.0, np.floor(acc[2] * inv + 0.5))))


def resample_colors(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics,
                    T_world_cam: np.ndarray, sources: SourceStack, depth_tol: float = 0.05) -> np.ndarray:
    """:func:`resample_colors_ref` in numba (one parallel pass per source view). Returns a new uint8 (H, W, 3)."""
    _check(color, depth_m, source, K)
    out = np.array(color, np.uint8, order="C")
    tg = _Target(float(K.fx), float(K.fy), float(K.cx), float(K.cy))
    d = np.ascontiguousarray(depth_m, np.float32)
    src = np.ascontiguousarray(source, np.int32)
    for view_id in np.flatnonzero(sources.lut >= 0):
        j = int(sources.lut[view_id])
        P = np.ascontiguousarray(source_projection(K, T_world_cam, sources, j))
        _resample_view_kernel(d, src, np.int32(view_id), tg, sources.colors[j], sources.depths[j], P,
                              float(depth_tol), out)
    return out
