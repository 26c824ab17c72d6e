"""Backward colour sampling: the colour of each rendered pixel read from its source view's image.

The forward warp decides, per target pixel, the surface (depth) and the view that sees it, but a
one-pixel splat carries the colour of the *nearest* source pixel, up to half a pixel off, and a crack
filled by the median carries a neighbour's colour. This stage replaces both: the target pixel is
back-projected with its depth (target camera -> world -> source camera) and its colour is
interpolated bilinearly in the source image at the exact sub-pixel position it projects to.
Taps whose source depth disagrees with the projected depth by more than ``depth_tol`` (relative)
are dropped and the rest renormalised, so colours never bleed across a depth edge; a pixel with no
valid tap keeps its splatted colour.

Reference: :func:`resample_colors_ref` (numpy, float64); fast paths: :func:`resample_colors`
(numba) and :func:`presim.synthesis.torch_kernels.resample_colors_torch`, tested against it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numba as nb
import numpy as np

from presim.geometry import Intrinsics
from presim.synthesis.threads import parallel_kernel

__all__ = ["SourceImage", "SourceStack", "stack_sources", "resample_colors_ref", "resample_colors"]


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


class SourceStack(NamedTuple):
    """Several source images packed for the kernels (flat arrays + per-view offsets)."""

    lut: np.ndarray
    """int32 (max_id + 1,): view id -> row of the per-view arrays, -1 = not given."""
    color: np.ndarray
    """uint8 (sum h w, 3)."""
    depth: np.ndarray
    """float32 (sum h w,)."""
    offset: np.ndarray
    """int64 (n,): first pixel of each view."""
    size: np.ndarray
    """int64 (n, 2): (w, h)."""
    intr: np.ndarray
    """float64 (n, 4): fx, fy, cx, cy."""
    T: np.ndarray
    """float64 (n, 3, 4): world -> view camera."""


def stack_sources(ids: Sequence[int], images: Sequence[SourceImage]) -> SourceStack:
    """Pack ``images`` of the views ``ids`` (scene frame indices) for the kernels."""
    n = len(ids)
    lut = np.full(max(ids, default=-1) + 1, -1, np.int32)
    sizes = np.array([(im.K.width, im.K.height) for im in images], np.int64).reshape(n, 2)
    off = np.zeros(n, np.int64)
    if n:
        off[1:] = np.cumsum(sizes[:, 0] * sizes[:, 1])[:-1]
    for j, v in enumerate(ids):
        lut[v] = j
    color = np.concatenate([im.color.reshape(-1, 3) for im in images]) if n else np.zeros((0, 3), np.uint8)
    depth = np.concatenate([im.depth_m.reshape(-1) for im in images]) if n else np.zeros(0, np.float32)
    intr = np.array([(im.K.fx, im.K.fy, im.K.cx, im.K.cy) for im in images], np.float64).reshape(n, 4)
    T = np.array([np.asarray(im.T_cam_world, np.float64)[:3] for im in images]).reshape(n, 3, 4)
    return SourceStack(lut, np.ascontiguousarray(color), np.ascontiguousarray(depth, np.float32), off, sizes, intr, T)


def _check(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics) -> None:
    H, W = K.height, K.width
    if color.shape != (H, W, 3) or depth_m.shape != (H, W) or source.shape != (H, W):
        raise ValueError(f"resample: need color (H, W, 3), depth (H, W), source (H, W) of {H}x{W}, got "
                         f"{color.shape}, {depth_m.shape}, {source.shape}")


def resample_colors_ref(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics,
                        T_world_cam: np.ndarray, sources: SourceStack, depth_tol: float = 0.05) -> np.ndarray:
    """Reference (numpy, float64). Pixels with ``source`` < 0, depth 0, a source not in ``sources``,
    a projection behind the source camera or outside ``[0, w - 1] x [0, h - 1]``, or no tap within
    ``depth_tol`` keep ``color``; the others get ``floor(sum(w c) / sum(w) + 0.5)`` over the four
    bilinear taps ``w`` of the valid ones. Returns a new uint8 (H, W, 3)."""
    _check(color, depth_m, source, K)
    out = color.copy()
    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W]
    s = source.astype(np.int64)
    ok = (s >= 0) & (depth_m > 0)
    ok[ok] &= s[ok] < len(sources.lut)
    j = np.full(s.shape, -1, np.int64)
    j[ok] = sources.lut[s[ok]]
    ok &= j >= 0
    u, v, d, j = u[ok].astype(np.float64), v[ok].astype(np.float64), depth_m[ok].astype(np.float64), j[ok]
    p = np.stack([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, d, np.ones_like(d)])
    X = np.asarray(T_world_cam, np.float64)[:3] @ p
    Xh = np.concatenate([X, np.ones((1, X.shape[1]))])
    Ps = np.einsum("nij,jn->in", sources.T[j], Xh)
    zs = Ps[2]
    fx, fy, cx, cy = sources.intr[j].T
    ws, hs = sources.size[j].T
    with np.errstate(divide="ignore", invalid="ignore"):
        us = fx * Ps[0] / zs + cx
        vs = fy * Ps[1] / zs + cy
    inside = (zs > 0) & (us >= 0) & (us <= ws - 1) & (vs >= 0) & (vs <= hs - 1)
    us, vs = np.where(inside, us, 0.0), np.where(inside, vs, 0.0)
    u0, v0 = np.floor(us).astype(np.int64), np.floor(vs).astype(np.int64)
    a, b = us - u0, vs - v0
    u1, v1 = np.minimum(u0 + 1, ws - 1), np.minimum(v0 + 1, hs - 1)
    acc = np.zeros((len(d), 3))
    wsum = np.zeros(len(d))
    for uu, vv, w in ((u0, v0, (1 - a) * (1 - b)), (u1, v0, a * (1 - b)), (u0, v1, (1 - a) * b), (u1, v1, a * b)):
        q = sources.offset[j] + vv * ws + uu
        q = np.where(inside, q, 0)
        ds = sources.depth[q].astype(np.float64) if len(sources.depth) else np.zeros(len(q))
        good = inside & (ds > 0) & (np.abs(ds - zs) <= depth_tol * zs)
        w = np.where(good, w, 0.0)
        acc += w[:, None] * sources.color[q].astype(np.float64)
        wsum += w
    use = wsum > 1e-9
    vals = np.floor(acc[use] / wsum[use, None] + 0.5).clip(0, 255).astype(np.uint8)
    rows, cols = np.nonzero(ok)
    out[rows[use], cols[use]] = vals
    return out


class _Target(NamedTuple):
    M: np.ndarray  # float64 (3, 4): target camera -> world
    fx: float
    fy: float
    cx: float
    cy: float


@parallel_kernel(cache=True, error_model="numpy")
def _resample_kernel(color, depth, source, tg, st, tol, out):  # pragma: no cover
    # resample_colors_ref per pixel (same float64 formulas, taps in the same order).
    H, W = depth.shape
    M = tg.M
    nlut = st.lut.shape[0]
    for v in nb.prange(H):
        for u in range(W):
            out[v, u, 0] = color[v, u, 0]
            out[v, u, 1] = color[v, u, 1]
            out[v, u, 2] = color[v, u, 2]
            s = source[v, u]
            d = np.float64(depth[v, u])
            if s < 0 or s >= nlut or not d > 0.0:
                continue
            j = st.lut[s]
            if j < 0:
                continue
            xc = (u - tg.cx) / tg.fx * d
            yc = (v - tg.cy) / tg.fy * d
            xw = M[0, 0] * xc + M[0, 1] * yc + M[0, 2] * d + M[0, 3]
            yw = M[1, 0] * xc + M[1, 1] * yc + M[1, 2] * d + M[1, 3]
            zw = M[2, 0] * xc + M[2, 1] * yc + M[2, 2] * d + M[2, 3]
            T = st.T[j]
            xs = T[0, 0] * xw + T[0, 1] * yw + T[0, 2] * zw + T[0, 3]
            ys = T[1, 0] * xw + T[1, 1] * yw + T[1, 2] * zw + T[1, 3]
            zs = T[2, 0] * xw + T[2, 1] * yw + T[2, 2] * zw + T[2, 3]
            if not zs > 0.0:
                continue
            ws = st.size[j, 0]
            hs = st.size[j, 1]
            us = st.intr[j, 0] * xs / zs + st.intr[j, 2]
            vs = st.intr[j, 1] * ys / zs + st.intr[j, 3]
            if not (us >= 0.0 and us <= ws - 1 and vs >= 0.0 and vs <= hs - 1):
                continue
            u0 = np.int64(np.floor(us))
            v0 = np.int64(np.floor(vs))
            a = us - u0
            b = vs - v0
            u1 = min(u0 + 1, ws - 1)
            v1 = min(v0 + 1, hs - 1)
            base = st.offset[j]
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            wsum = 0.0
            for t in range(4):
                uu = u1 if t == 1 or t == 3 else u0
                vv = v1 if t >= 2 else v0
                w = (a if t == 1 or t == 3 else 1.0 - a) * (b if t >= 2 else 1.0 - b)
                q = base + vv * ws + uu
                ds = np.float64(st.depth[q])
                if ds > 0.0 and abs(ds - zs) <= tol * zs:
                    c0 += w * st.color[q, 0]
                    c1 += w * st.color[q, 1]
                    c2 += w * st.color[q, 2]
                    wsum += w
            if wsum > 1e-9:
                out[v, u, 0] = np.uint8(min(255.0, max(0.0, np.floor(c0 / wsum + 0.5))))
                out[v, u, 1] = np.uint8(min(255.0, max(0.0, np.floor(c1 / wsum + 0.5))))
                out[v, u, 2] = np.uint8(min(255.0, max(0.0, np.floor(c2 / wsum + 0.5))))


def resample_colors(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics,
                    T_world_cam: np.ndarray, sources: SourceStack, depth_tol: float = 0.05) -> np.ndarray:
    """:func:`resample_colors_ref` in numba (parallel over rows). Returns a new uint8 (H, W, 3)."""
    _check(color, depth_m, source, K)
    out = np.empty_like(color)
    tg = _Target(np.ascontiguousarray(np.asarray(T_world_cam, np.float64)[:3]), float(K.fx), float(K.fy),
                 float(K.cx), float(K.cy))
    _resample_kernel(np.ascontiguousarray(color), np.ascontiguousarray(depth_m, np.float32),
                     np.ascontiguousarray(source, np.int32), tg, sources, float(depth_tol), out)
    return out
