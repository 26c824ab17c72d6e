"""Multi-view blending instead of winner-takes-all (beyond the thesis; unstructured-lumigraph weights).

The adaptive loop (:func:`presim.synthesis.core.synthesize_frame`) gives every covered target pixel
one winning view and the front surface depth ``d(p)``. Blending then mixes, per pixel, the colours
of all views (among the first ``max_views`` the loop warped) that see the **same surface** there:
view ``k`` is a candidate at ``p`` when its front-most warped depth ``d_k(p)`` agrees with ``d(p)``
within ``depth_tol_rel * d(p)``; the winner always is (with its crack-filtered colour). Weights,
after Buehler et al.'s unstructured lumigraph rendering (ULR):

- **angle** ``a_k``: the angle at the surface point ``X`` between the target ray ``X - C_t`` and
  view k's ray ``X - C_k`` (the colour a view recorded is most likely what the target sees when
  both look at ``X`` along the same ray), computed as the chord ``sqrt(2 - 2 cos)`` of the unit
  rays (the angle in radians within 0.1 % below 8 degrees, no arccos);
- **resolution** ``r_k = max(0, |X - C_k| / |X - C_t| - 1)``: a view farther from the surface
  than the target samples it more coarsely (magnified, blurrier);
- penalty ``P_k = a_k + resolution_weight * r_k``; ULR's k-nearest threshold becomes a softened
  inverse: ``w_k = feather_k(p) * quality_k / (P_k + penalty_eps)``;
- **feathering**: ``feather_k(p)`` ramps from 0 at the border of view k's coverage in the target
  to 1 about ``feather_px / 2`` pixels inside it (:func:`feather_map`), so a view fades in and
  out instead of leaving a visible seam (the winner keeps at least ``1 / feather_px``);
- ``quality_k``: a per-view factor from the caller (sharpness, :mod:`presim.synthesis.sharpness`;
  1 by default).

The blended colour ``sum_k w_k c_k / sum_k w_k`` replaces the winner's colour only where at least two
views agree; depth, validity and source view stay those of the winner. Identical candidate colours
give exactly that colour back. :func:`blend_reference` is the plain numpy definition the numba
kernel is tested against.

Cost: per blended view one plain z-buffer warp + front-to-back composite (no crack filter: cracks
only mean fewer candidates), one closing + distance transform, and the per-pixel weight kernel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import cv2
import numba as nb
import numpy as np

from presim.geometry import Intrinsics
from presim.synthesis.warp import _FASTMATH as _WARP_FASTMATH

__all__ = ["BlendConfig", "BlendInput", "feather_map", "front_image_points", "front_of_layers", "blend_reference",
           "blend_numba", "blend_frame"]


@dataclass(frozen=True)
class BlendConfig:
    """Knobs of the per-pixel blend (``RenderConfig.blend_*`` fields)."""

    max_views: int = 3
    """Blend among the first this many views the adaptive loop warped (winner included)."""
    depth_tol_rel: float = 0.02
    """A view is a candidate at a pixel when its depth agrees with the front surface within this
    fraction of the depth."""
    resolution_weight: float = 1.0
    """Weight of the resolution penalty against the angle penalty (radians)."""
    penalty_eps: float = 0.02
    """Added to the penalty before inverting it (rad; bounds the weight of a view on the target ray)."""
    feather_px: float = 8.0
    """Views fade in over this many pixels from the border of their coverage (1 = no feathering)."""

    def __post_init__(self) -> None:
        if self.max_views < 1:
            raise ValueError("BlendConfig: max_views must be >= 1")
        if not 0.0 < self.depth_tol_rel < 1.0:
            raise ValueError("BlendConfig: depth_tol_rel must be in (0, 1)")
        if self.penalty_eps <= 0 or self.feather_px < 1 or self.resolution_weight < 0:
            raise ValueError("BlendConfig: penalty_eps > 0, feather_px >= 1, resolution_weight >= 0")


@dataclass(frozen=True)
class BlendInput:
    """The loop's result and the candidates' warped images, for one target camera."""

    color: np.ndarray
    """uint8 (H, W, 3) winner colours."""
    depth_m: np.ndarray
    """float32 (H, W) front surface, 0 = uncovered."""
    source: np.ndarray
    """int32 (H, W) winner view id, -1 = none."""
    view_ids: np.ndarray
    """int32 (n,) ids of the candidate views."""
    view_depth_m: np.ndarray
    """float32 (n, H, W) each candidate's front-most warped depth, 0 = empty."""
    view_color: np.ndarray
    """uint8 (n, H, W, 3) their colours (already photometrically corrected)."""
    feather: np.ndarray
    """float32 (n, H, W) feathering factor in (0, 1]."""
    centres: np.ndarray
    """float64 (n, 3) candidate camera centres, world."""
    quality: np.ndarray
    """float64 (n,) per-view factor (sharpness), > 0."""


def feather_map(depth_m: np.ndarray, feather_px: float) -> np.ndarray:
    """Feathering factor of a view's coverage (float32 (H, W), 0 outside it): the fraction ``m`` of
    covered pixels in a ``feather_px`` box around each pixel, mapped by ``clip(2 m - 1, 0, 1)`` —
    0 at a straight coverage border, 1 from ``feather_px / 2`` inside it; isolated one-pixel cracks
    barely lower it. A box filter is O(1) per pixel (a distance transform cost ~3x more)."""
    cov = (depth_m > 0).astype(np.float32)
    if feather_px <= 1:
        return cov
    k = max(3, int(round(feather_px)) | 1)
    m = cv2.blur(cov, (k, k), borderType=cv2.BORDER_REPLICATE)
    f = np.clip(2.0 * m - 1.0, 0.0, 1.0)
    f *= cov
    return f


def front_image_points(view, T_cam_world: np.ndarray, K: Intrinsics, near_m: float,
                       depth_out: np.ndarray, color_out: np.ndarray) -> None:
    """Front-most surface of a prepared view (:class:`~presim.synthesis.warp.ViewPoints`) in the
    target, written into ``depth_out`` (float32 (H, W)) / ``color_out`` (uint8 (H, W, 3)): all its
    points z-buffered as one layer (nearest pixel, smallest z, the projection of the warp kernel),
    no crack filter."""
    M = np.ascontiguousarray(np.asarray(T_cam_world, np.float64)[:3, :4], np.float32)
    _front_warp_kernel(view.xyz_world, view.rgb, M, np.float32(K.fx), np.float32(K.fy), np.float32(K.cx),
                       np.float32(K.cy), np.float32(near_m), depth_out, color_out)


@nb.njit(fastmath=_WARP_FASTMATH, cache=True)  # the warp kernel's flags: bit-equal projections
def _front_warp_kernel(xyz, rgb, M, fx, fy, cx, cy, near, zbuf, cbuf):  # pragma: no cover
    # Same arithmetic as presim.synthesis.warp._warp_layers_kernel with one layer (tested equal).
    H, W = zbuf.shape
    zbuf[:] = 0.0
    cbuf[:] = 0
    for i in range(xyz.shape[0]):
        x = xyz[i, 0]
        y = xyz[i, 1]
        z = xyz[i, 2]
        zc = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
        if not (zc > near):
            continue
        xc = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]
        yc = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]
        uf = fx * xc / zc + cx + np.float32(0.5)
        vf = fy * yc / zc + cy + np.float32(0.5)
        if not (uf >= 0.0 and uf < W and vf >= 0.0 and vf < H):
            continue
        ui = int(uf)
        vi = int(vf)
        cur = zbuf[vi, ui]
        if cur == 0.0 or zc < cur:
            zbuf[vi, ui] = zc
            cbuf[vi, ui, 0] = rgb[i, 0]
            cbuf[vi, ui, 1] = rgb[i, 1]
            cbuf[vi, ui, 2] = rgb[i, 2]


def front_of_layers(layer_depth_m: np.ndarray, layer_color: np.ndarray, depth_out: np.ndarray,
                    color_out: np.ndarray) -> None:
    """Front-most surface of an already warped view (the loop's (L, H, W) z-buffered layers): per
    pixel the smallest depth over the layers, written into ``depth_out`` / ``color_out`` (the same
    surface :func:`front_image_points` z-buffers, without warping the view again)."""
    _front_of_layers_kernel(layer_depth_m, layer_color, depth_out, color_out)


@nb.njit(parallel=True, cache=True)
def _front_of_layers_kernel(ld, lc, zout, cout):  # pragma: no cover
    L, H, W = ld.shape
    for v in nb.prange(H):
        for u in range(W):
            best = 0.0
            bl = -1
            for l in range(L):
                z = ld[l, v, u]
                if z > 0.0 and (bl < 0 or z < best):
                    best = z
                    bl = l
            zout[v, u] = best
            if bl < 0:
                cout[v, u, 0] = 0
                cout[v, u, 1] = 0
                cout[v, u, 2] = 0
            else:
                cout[v, u, 0] = lc[bl, v, u, 0]
                cout[v, u, 1] = lc[bl, v, u, 1]
                cout[v, u, 2] = lc[bl, v, u, 2]


def _world_points(K: Intrinsics, T_world_cam: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    H, W = depth_m.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    xc = (u - K.cx) / K.fx * depth_m
    yc = (v - K.cy) / K.fy * depth_m
    P = np.stack([xc, yc, depth_m.astype(np.float64)], -1)
    return P @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def blend_reference(inp: BlendInput, K: Intrinsics, T_world_cam: np.ndarray, config: BlendConfig) -> np.ndarray:
    """Plain numpy definition of the blend (see module docstring); returns uint8 (H, W, 3)."""
    d = inp.depth_m.astype(np.float64)
    X = _world_points(K, T_world_cam, d)
    Ct = T_world_cam[:3, 3]
    rt = X - Ct
    lt = np.linalg.norm(rt, axis=-1)
    num = np.zeros(d.shape + (3,))
    den = np.zeros(d.shape)
    cnt = np.zeros(d.shape, np.int64)
    for k in range(len(inp.view_ids)):
        win = inp.source == inp.view_ids[k]
        dk = inp.view_depth_m[k].astype(np.float64)
        agree = (d > 0) & (dk > 0) & (np.abs(dk - d) <= config.depth_tol_rel * d)
        use = (d > 0) & (win | agree)
        rk = X - inp.centres[k]
        lk = np.linalg.norm(rk, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cosang = np.clip(np.sum(rt * rk, -1) / (lt * lk), -1.0, 1.0)
            ang = np.sqrt(2.0 - 2.0 * cosang)  # chord of the angle: = angle to 0.1 % below 8 degrees
            res = np.maximum(0.0, lk / lt - 1.0)
        pen = ang + config.resolution_weight * res
        f = np.where(win, np.maximum(inp.feather[k], 1.0 / config.feather_px), inp.feather[k])
        w = np.where(use, f * inp.quality[k] / (pen + config.penalty_eps), 0.0)
        col = np.where(win[..., None], inp.color, inp.view_color[k]).astype(np.float64)
        num += w[..., None] * col
        den += w
        cnt += use
    out = inp.color.copy()
    m = (cnt >= 2) & (den > 0)
    out[m] = np.clip(np.floor(num[m] / den[m][:, None] + 0.5), 0, 255).astype(np.uint8)
    return out


@nb.njit(parallel=True, cache=True)
def _blend_kernel(color, depth, source, ids, vdepth, vcolor, feather, centres, quality, M, fx, fy, cx, cy,
                  tol, res_w, eps, min_f, out):  # pragma: no cover
    H, W = depth.shape
    n = ids.shape[0]
    ctx, cty, ctz = M[0, 3], M[1, 3], M[2, 3]
    for v in nb.prange(H):
        for u in range(W):
            out[v, u, 0] = color[v, u, 0]
            out[v, u, 1] = color[v, u, 1]
            out[v, u, 2] = color[v, u, 2]
            d = np.float64(depth[v, u])
            if d <= 0.0:
                continue
            src = source[v, u]
            # Cheap pass first: most pixels have a single agreeing view and keep the winner's colour.
            cnt = 0
            for k in range(n):
                if src == ids[k]:
                    cnt += 1
                else:
                    dk = np.float64(vdepth[k, v, u])
                    if dk > 0.0 and abs(dk - d) <= tol * d:
                        cnt += 1
            if cnt < 2:
                continue
            xc = (u - cx) / fx * d
            yc = (v - cy) / fy * d
            X0 = M[0, 0] * xc + M[0, 1] * yc + M[0, 2] * d + ctx
            X1 = M[1, 0] * xc + M[1, 1] * yc + M[1, 2] * d + cty
            X2 = M[2, 0] * xc + M[2, 1] * yc + M[2, 2] * d + ctz
            t0, t1, t2 = X0 - ctx, X1 - cty, X2 - ctz
            lt = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            den = 0.0
            for k in range(n):
                win = src == ids[k]
                if not win:
                    dk = np.float64(vdepth[k, v, u])
                    if dk <= 0.0 or abs(dk - d) > tol * d:
                        continue
                r0, r1, r2 = X0 - centres[k, 0], X1 - centres[k, 1], X2 - centres[k, 2]
                lk = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                c = (t0 * r0 + t1 * r1 + t2 * r2) / (lt * lk)
                c = min(1.0, max(-1.0, c))
                pen = np.sqrt(2.0 - 2.0 * c) + res_w * max(0.0, lk / lt - 1.0)
                f = np.float64(feather[k, v, u])
                if win and f < min_f:
                    f = min_f
                w = f * quality[k] / (pen + eps)
                if win:
                    s0 += w * color[v, u, 0]
                    s1 += w * color[v, u, 1]
                    s2 += w * color[v, u, 2]
                else:
                    s0 += w * vcolor[k, v, u, 0]
                    s1 += w * vcolor[k, v, u, 1]
                    s2 += w * vcolor[k, v, u, 2]
                den += w
            if den > 0.0:
                out[v, u, 0] = np.uint8(min(255.0, max(0.0, np.floor(s0 / den + 0.5))))
                out[v, u, 1] = np.uint8(min(255.0, max(0.0, np.floor(s1 / den + 0.5))))
                out[v, u, 2] = np.uint8(min(255.0, max(0.0, np.floor(s2 / den + 0.5))))


def blend_numba(inp: BlendInput, K: Intrinsics, T_world_cam: np.ndarray, config: BlendConfig) -> np.ndarray:
    """numba fast path of :func:`blend_reference` (same result up to float rounding at .5 levels)."""
    out = np.empty_like(inp.color)
    _blend_kernel(inp.color, inp.depth_m, inp.source, inp.view_ids.astype(np.int32),
                  inp.view_depth_m, inp.view_color, inp.feather, np.ascontiguousarray(inp.centres, np.float64),
                  np.ascontiguousarray(inp.quality, np.float64), np.ascontiguousarray(T_world_cam, np.float64),
                  float(K.fx), float(K.fy), float(K.cx), float(K.cy), float(config.depth_tol_rel),
                  float(config.resolution_weight), float(config.penalty_eps), 1.0 / float(config.feather_px), out)
    return out


def blend_frame(views: Sequence[int], color: np.ndarray, depth_m: np.ndarray, source: np.ndarray,
                T_world_cam: np.ndarray, K: Intrinsics, config: BlendConfig,
                front_image: Callable[[int, np.ndarray, np.ndarray], None],
                centre_of: Callable[[int], np.ndarray], quality_of: Callable[[int], float] | None = None,
                color_transform: Callable[[int, np.ndarray], np.ndarray] | None = None,
                use_reference: bool = False, buffers: dict | None = None) -> tuple[np.ndarray, float]:
    """Blend the first ``config.max_views`` of ``views`` into the loop's winner image.

    Args:
        views: the views the loop warped, in order; color / depth_m / source: its merged result.
        T_world_cam, K: target camera.
        front_image: ``front_image(id, depth_out, color_out)`` writes the view's front-most warped
            surface in the target into ``depth_out`` (float32 (H, W)) and ``color_out`` (uint8
            (H, W, 3)) (a plain z-buffer warp, :func:`front_image_points`, or the loop's own warp,
            :func:`front_of_layers`).
        centre_of: ``centre_of(id)`` -> (3,) camera centre, world.
        quality_of: per-view factor (sharpness); None = 1.
        color_transform: the frame's per-view photometric correction (the core's hook), or None.
        use_reference: run :func:`blend_reference` instead of the numba kernel (tests).
        buffers: a dict the caller keeps across frames; the per-view stacks are reused from it.
    Returns:
        ``(blended color uint8 (H, W, 3), milliseconds)``.
    """
    t0 = time.perf_counter()
    use = [int(v) for v in list(views)[:config.max_views]]
    if len(use) < 2:
        return color, (time.perf_counter() - t0) * 1e3
    H, W = depth_m.shape
    n = len(use)
    buf = buffers if buffers is not None else {}
    if buf.get("shape") != (config.max_views, H, W):  # allocated once per output size
        buf["shape"] = (config.max_views, H, W)
        buf["d"] = np.empty((config.max_views, H, W), np.float32)
        buf["c"] = np.empty((config.max_views, H, W, 3), np.uint8)
        buf["f"] = np.empty((config.max_views, H, W), np.float32)
    vd, vc, fe = buf["d"][:n], buf["c"][:n], buf["f"][:n]
    for i, v in enumerate(use):
        front_image(v, vd[i], vc[i])
        if color_transform is not None:
            vc[i] = color_transform(v, vc[i])
        fe[i] = feather_map(vd[i], config.feather_px)
    inp = BlendInput(color, depth_m, source, np.asarray(use, np.int32), vd, vc, fe,
                     np.stack([np.asarray(centre_of(v), np.float64) for v in use]),
                     np.array([1.0 if quality_of is None else float(quality_of(v)) for v in use]))
    out = (blend_reference if use_reference else blend_numba)(inp, K, np.asarray(T_world_cam, np.float64), config)
    return out, (time.perf_counter() - t0) * 1e3
