"""Multi-view blending instead of winner-takes-all (beyond the thesis; unstructured-lumigraph weights).

Among the first ``max_views`` warped views, view ``k`` counts at pixel ``p`` when its front-most depth agrees with
the winner's ``d(p)`` within ``depth_tol_rel * d(p)`` (the winner always does), with weight
``feather_k(p) * quality_k / (a_k + resolution_weight * r_k + penalty_eps)``: ``a_k`` the chord of the angle
between target and view rays at the surface point, ``r_k = max(0, |X - C_k| / |X - C_t| - 1)``, ``feather_k``
(:func:`~presim.imaging.feather.feather_map`; the winner keeps >= ``1 / feather_px``). Where >= 2 views count, the
weighted mean replaces the winner's colour. Reference :func:`blend_reference`; numba :func:`blend_numba`."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Sequence

import numba as nb
import numpy as np

from presim.geometry import Intrinsics
from presim.imaging.feather import coverage_counts, feather_box, feather_map
from presim.numba_threads import parallel_kernel

__all__ = ["BlendConfig", "BlendInput", "front_of_layers", "blend_reference",
           "blend_numba", "blend_stacks", "blend_frame"]


@dataclass(frozen=True)
class BlendConfig:
    """Knobs of the per-pixel blend (``RenderConfig.blend_*`` fields)."""

    max_views: int = 3
    """Blend among the first this many views the adaptive loop warped (winner included)."""
    depth_tol_rel: float = 0.02
    """A view is a candidate where its depth agrees with the front surface within this fraction of it."""
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


class BlendInput(NamedTuple):
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
    """uint8 (n, H, W, 3) their colours (any strides; the kernel reads planar ``(n, 3, H, W)``)."""
    centres: np.ndarray
    """float64 (n, 3) candidate camera centres, world."""
    quality: np.ndarray
    """float64 (n,) per-view factor (sharpness), > 0."""
    feather_count: np.ndarray | None = None
    """Optional (n, H, W) :func:`coverage_counts` (None = computed; unused by the reference)."""


def front_of_layers(layer_depth_m: np.ndarray, layer_color: np.ndarray, depth_out: np.ndarray,
                    color_out: np.ndarray) -> None:
    """Front-most surface of an already warped view (the loop's (L, H, W) layers): smallest depth per pixel into
    ``depth_out`` / ``color_out`` (planar colour allowed): the one-layer z-buffer of the view's points (tested)."""
    _front_of_layers_kernel(layer_depth_m, layer_color, depth_out, color_out.transpose(2, 0, 1))


@parallel_kernel(fastmath=True, cache=True, error_model="numpy")
def _front_of_layers_kernel(ld, lc, zout, cp):  # pragma: no cover
    # Per row: depths first (branch-free, vectorises), then one colour gather into the planes cp (3, H, W).
    L, H, W = ld.shape
    for v in nb.prange(H):
        best = np.empty(W, np.int32)
        zr = zout[v]
        for u in range(W):
            zr[u] = ld[0, v, u]
            best[u] = 0
        for l in range(1, L):
            lr = ld[l, v]
            for u in range(W):
                z = lr[u]
                b = zr[u]
                take = (z > 0.0) & ((b == 0.0) | (z < b))
                zr[u] = z if take else b
                best[u] = l if take else best[u]
        c0 = cp[0, v]
        c1 = cp[1, v]
        c2 = cp[2, v]
        for u in range(W):
            bl = best[u]
            c0[u] = lc[bl, v, u, 0]
            c1[u] = lc[bl, v, u, 1]
            c2[u] = lc[bl, v, u, 2]


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
        fk = feather_map(inp.view_depth_m[k], config.feather_px)
        f = np.where(win, np.maximum(fk, 1.0 / config.feather_px), fk)
        w = np.where(use, f * inp.quality[k] / (pen + config.penalty_eps), 0.0)
        col = np.where(win[..., None], inp.color, inp.view_color[k]).astype(np.float64)
        num += w[..., None] * col
        den += w
        cnt += use
    out = inp.color.copy()
    m = (cnt >= 2) & (den > 0)
    out[m] = np.clip(np.floor(num[m] / den[m][:, None] + 0.5), 0, 255).astype(np.uint8)
    return out


class _BlendCam(NamedTuple):
    M: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    fscale: float
    tol: float
    res_w: float
    eps: float
    min_f: float


@parallel_kernel(fastmath=True, error_model="numpy", cache=True)
def _blend_kernel(a, cam, out):  # pragma: no cover
    # Row by row; branch-free float32 inner loops over contiguous rows (planar vcp (n, 3, H, W)) vectorise.
    # Same formulas and order as blend_reference; feathering from the box counts exactly as feather_map.
    color, depth, source, ids, vdepth, vcp = a.color, a.depth_m, a.source, a.view_ids, a.view_depth_m, a.view_color
    fcount, centres, quality = a.feather_count, a.centres, a.quality
    M, fx, fy, cx, cy = cam.M, cam.fx, cam.fy, cam.cx, cam.cy
    fscale, tol, res_w, eps, min_f = cam.fscale, cam.tol, cam.res_w, cam.eps, cam.min_f
    H, W = depth.shape
    n = ids.shape[0]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    two = np.float32(2.0)
    tiny = np.float32(1e-12)
    for v in nb.prange(H):
        t0 = np.empty(W, np.float32)
        t1 = np.empty(W, np.float32)
        t2 = np.empty(W, np.float32)
        lt = np.empty(W, np.float32)
        s0 = np.zeros(W, np.float32)
        s1 = np.zeros(W, np.float32)
        s2 = np.zeros(W, np.float32)
        den = np.zeros(W, np.float32)
        cnt = np.zeros(W, np.int32)
        c0r = np.empty(W, np.uint8)  # the winner colours, de-interleaved
        c1r = np.empty(W, np.uint8)
        c2r = np.empty(W, np.uint8)
        dr = depth[v]
        sr = source[v]
        cr = color[v]
        yn = (np.float32(v) - cy) / fy
        for u in range(W):
            d = dr[u]
            xn = (np.float32(u) - cx) / fx
            a0 = (M[0, 0] * xn + M[0, 1] * yn + M[0, 2]) * d  # target ray to the surface point
            a1 = (M[1, 0] * xn + M[1, 1] * yn + M[1, 2]) * d
            a2 = (M[2, 0] * xn + M[2, 1] * yn + M[2, 2]) * d
            t0[u] = a0
            t1[u] = a1
            t2[u] = a2
            lt[u] = max(np.sqrt(a0 * a0 + a1 * a1 + a2 * a2), tiny)
            c0r[u] = cr[u, 0]
            c1r[u] = cr[u, 1]
            c2r[u] = cr[u, 2]
        for k in range(n):
            idk = ids[k]
            e0 = M[0, 3] - centres[k, 0]  # target centre - view centre
            e1 = M[1, 3] - centres[k, 1]
            e2 = M[2, 3] - centres[k, 2]
            qk = quality[k]
            vdr = vdepth[k, v]
            fcr = fcount[k, v]
            v0 = vcp[k, 0, v]
            v1 = vcp[k, 1, v]
            v2 = vcp[k, 2, v]
            for u in range(W):
                d = dr[u]
                dk = vdr[u]
                win = sr[u] == idk
                use = (d > zero) & (win | ((dk > zero) & (abs(dk - d) <= tol * d)))
                r0 = t0[u] + e0
                r1 = t1[u] + e1
                r2 = t2[u] + e2
                lk = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                ltu = lt[u]
                c = (t0[u] * r0 + t1[u] * r1 + t2[u] * r2) / (ltu * max(lk, tiny))
                c = min(one, max(-one, c))
                pen = np.sqrt(two - two * c) + res_w * max(zero, lk / ltu - one)
                m = np.float32(np.float64(fcr[u]) * fscale)  # feather_map: box mean, as OpenCV rounds it
                fm = min(one, max(zero, two * m - one))
                f = fm if dk > zero else zero
                f = max(f, min_f) if win else f
                w = f * qk / (pen + eps) if use else zero
                den[u] += w
                cnt[u] += np.int32(use)
                a0 = c0r[u]
                a1 = c1r[u]
                a2 = c2r[u]
                b0 = v0[u]
                b1 = v1[u]
                b2 = v2[u]
                s0[u] += w * np.float32(a0 if win else b0)
                s1[u] += w * np.float32(a1 if win else b1)
                s2[u] += w * np.float32(a2 if win else b2)
        for u in range(W):  # blended value where >= 2 views agree, else the winner's
            ok = (cnt[u] >= 2) & (den[u] > zero)
            inv = one / den[u]
            x0 = np.uint8(min(np.float32(255.0), max(zero, np.floor(s0[u] * inv + np.float32(0.5)))))
            x1 = np.uint8(min(np.float32(255.0), max(zero, np.floor(s1[u] * inv + np.float32(0.5)))))
            x2 = np.uint8(min(np.float32(255.0), max(zero, np.floor(s2[u] * inv + np.float32(0.5)))))
            c0r[u] = x0 if ok else c0r[u]
            c1r[u] = x1 if ok else c1r[u]
            c2r[u] = x2 if ok else c2r[u]
        orow = out[v]
        for u in range(W):
            orow[u, 0] = c0r[u]
            orow[u, 1] = c1r[u]
            orow[u, 2] = c2r[u]


def blend_numba(inp: BlendInput, K: Intrinsics, T_world_cam: np.ndarray, config: BlendConfig) -> np.ndarray:
    """numba fast path of :func:`blend_reference` (float32: equal except values within rounding of a .5 level or
    depths within rounding of the tolerance); feathers from :func:`coverage_counts`."""
    out = np.empty_like(inp.color)
    f32 = np.float32
    vcp = inp.view_color.transpose(0, 3, 1, 2)
    if not vcp.flags.c_contiguous:
        vcp = np.ascontiguousarray(vcp)
    counts = inp.feather_count
    if counts is None:
        counts = np.stack([coverage_counts(d, config.feather_px) for d in inp.view_depth_m])
    k = feather_box(config.feather_px)
    fscale = 1.0 if config.feather_px <= 1 else 1.0 / (k * k)  # no feathering: any count >= 1 gives 1
    arrays = inp._replace(view_ids=inp.view_ids.astype(np.int32), view_color=vcp, feather_count=counts,
                          centres=np.ascontiguousarray(inp.centres, np.float32),
                          quality=np.ascontiguousarray(inp.quality, np.float32))
    cam = _BlendCam(np.ascontiguousarray(T_world_cam, np.float32), f32(K.fx), f32(K.fy), f32(K.cx), f32(K.cy),
                    fscale, f32(config.depth_tol_rel), f32(config.resolution_weight), f32(config.penalty_eps),
                    f32(1.0 / float(config.feather_px)))
    _blend_kernel(arrays, cam, out)
    return out


def blend_stacks(buffers: dict, max_views: int, H: int, W: int, feather_px: float = 8.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-view ``(depth (n, H, W), color (n, H, W, 3), feather counts (n, H, W))`` stacks kept in ``buffers``
    (once per output size); slot ``i`` = ``i``-th blended view; colours planar ``(n, 3, H, W)`` memory."""
    dt = np.uint8 if feather_box(feather_px) ** 2 <= 255 else np.uint16
    if buffers.get("shape") != (max_views, H, W, dt):
        buffers["shape"] = (max_views, H, W, dt)
        buffers["d"] = np.empty((max_views, H, W), np.float32)
        buffers["c"] = np.empty((max_views, 3, H, W), np.uint8).transpose(0, 2, 3, 1)
        buffers["f"] = np.empty((max_views, H, W), dt)
    return buffers["d"], buffers["c"], buffers["f"]


def blend_frame(views: Sequence[int], color: np.ndarray, depth_m: np.ndarray, source: np.ndarray,
                T_world_cam: np.ndarray, K: Intrinsics, config: BlendConfig,
                front_image: Callable[[int, np.ndarray, np.ndarray], None],
                centre_of: Callable[[int], np.ndarray], quality_of: Callable[[int], float] | None = None,
                kernel: Callable[..., np.ndarray] | None = None, buffers: dict | None = None
                ) -> tuple[np.ndarray, float]:
    """Blend the first ``config.max_views`` of ``views`` into the loop's result: ``(color, ms)``.

    ``front_image(id, depth_out, color_out)`` writes a view's front surface (:func:`front_of_layers`);
    ``centre_of(id)``: its camera centre; ``quality_of``: its factor (None = 1);
    ``kernel``: :func:`blend_numba` (None), :func:`blend_reference` or a kernel of their contract (torch);
    ``buffers``: a dict kept across frames for the stacks."""
    t0 = time.perf_counter()
    kernel = kernel or blend_numba
    use = [int(v) for v in list(views)[:config.max_views]]
    if len(use) < 2:
        return color, (time.perf_counter() - t0) * 1e3
    H, W = depth_m.shape
    n = len(use)
    d_all, c_all, f_all = blend_stacks(buffers if buffers is not None else {}, config.max_views, H, W,
                                       config.feather_px)
    vd, vc, fc = d_all[:n], c_all[:n], f_all[:n]
    for i, v in enumerate(use):
        front_image(v, vd[i], vc[i])  # the caller may have filled slot i already (the loop's warp)
        if kernel is blend_numba:
            coverage_counts(vd[i], config.feather_px, out=fc[i])
    inp = BlendInput(color, depth_m, source, np.asarray(use, np.int32), vd, vc,
                     np.stack([np.asarray(centre_of(v), np.float64) for v in use]),
                     np.array([1.0 if quality_of is None else float(quality_of(v)) for v in use]),
                     fc if kernel is blend_numba else None)
    out = kernel(inp, K, np.asarray(T_world_cam, np.float64), config)
    return out, (time.perf_counter() - t0) * 1e3
