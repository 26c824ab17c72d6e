"""Multi-view depth refinement (thesis §3.4.1, Algorithm 1).

For one target frame and up to ten reference frames:

1. **Cost** of a depth hypothesis ``d`` at pixel ``p`` (eq. 3.1): ``C = C_pixel + patch_weight * C_patch``.

   - ``C_pixel`` (eq. 3.2): ``p`` is unprojected at ``d``, projected into every reference view and
     compared there: ``lambda * |x_p - x_r| + (1 - lambda) * |grad x_p - grad x_r|`` (colors in [0, 1],
     per-channel mean; gradients of the gray image). Only *front-most* correspondences count: when the
     reference's own depth says the projected point lies behind its surface (occluded there), that
     reference is skipped. Each reference's cost is truncated at ``truncation`` (robust to exposure
     changes and mismatches) and the costs are averaged. A depth no reference sees front-most costs
     ``unseen_cost`` (neutral, not maximal: see :class:`RefineConfig`).
   - ``C_patch`` (eq. 3.3-3.4): the thesis' ``diff`` (eq. 3.4) of ``p`` to each neighbour ``q`` of an
     ``n x n`` patch is used as an adaptive support weight ``w = exp(-diff / gamma)``, as PatchMatch
     stereo [BRR11] does, and the term is the weighted mean disagreement of ``d`` with the neighbours'
     depths (``min(|d - D_q| / (rel_tol * d), 1)``). Read literally, eq. 3.3 does not depend on the
     depth at all and so could not choose between depths; this reading keeps its ``diff`` and makes it
     edge preserving: a depth is cheap when it agrees with the neighbours of *similar color*.

2. **Propagation** (Alg. 1 lines 3-5), scan order, alternating forward and backward passes: when a
   pixel's cost is above the mean (finite) cost of its ``n x n`` patch, the depths of the patch's
   pixels are tried at ``p`` (the cost is re-evaluated at ``p``; copying a neighbour's cost as-is would
   compare photo-consistency of different pixels) and the lowest-cost one replaces ``p``'s depth and
   cost. Pixels without depth are always tried: they take a neighbour's depth only when its cost is
   below ``fill_max_cost``, the neighbour's color is similar (``fill_color_max``) and the chain of
   fills from an originally valid pixel is at most ``max_fill_hops`` long.

3. **Color-guided weighted median** [MHW+13]: each pixel takes the weighted median of the valid
   depths in a ``(2r+1)^2`` window, weights = color similarity x spatial Gaussian x confidence
   ``exp(-C_q / cost_sigma)``. Invalid pixels are filled only where the valid, similarly colored
   pixels carry at least ``median_min_support`` of the window's color/spatial weight; pixels that
   cannot be supported stay 0.

Two implementations: a numba fast path (default) and a slow, plain reference (``backend="reference"``)
used by tests on tiny inputs; both follow the same order of operations and must match.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numba as nb
import numpy as np

from presim.capture.sharpness import sharpness_score
from presim.geometry import Intrinsics, compose, invert

__all__ = ["RefineConfig", "RefView", "RefinedDepth", "refine_depth", "select_reference_views",
           "prepare_image", "reference_weights"]


@dataclass(frozen=True)
class RefineConfig:
    """Parameters of the depth refinement (defaults: thesis values where it gives them)."""

    num_refs: int = 10
    """Reference views per target (thesis: 10)."""
    max_ref_angle_deg: float = 60.0
    """References whose viewing direction differs more than this from the target's are not used."""
    lam: float = 0.9
    """lambda of eq. 3.2 / 3.4: weight of the color term vs the gradient term (thesis: 0.9)."""
    patch_size: int = 3
    """n of the n x n propagation / patch-cost window (thesis: 3)."""
    truncation: float = 0.3
    """Per-reference cost truncation (colors in [0, 1])."""
    unseen_cost: float = 0.1
    """C_pixel of a depth no reference sees front-most (all occluded or outside). Not the maximum:
    the strip a foreground edge hides from every other view is correct but unverifiable, and a
    maximal cost there lets foreground depths (which do project onto something) take it over."""
    occlusion_rel_tol: float = 0.03
    """A projected point deeper than ``ref_depth * (1 + tol)`` is occluded in that reference (not
    front-most) and the reference is skipped."""
    patch_weight: float = 0.3
    """Weight of C_patch relative to C_pixel (the thesis adds them with unstated scales)."""
    support_gamma: float = 0.05
    """gamma of the adaptive support weight exp(-diff / gamma) in C_patch."""
    depth_rel_tol: float = 0.02
    """Relative depth difference at which a neighbour fully disagrees in C_patch."""
    num_passes: int = 2
    """Propagation passes (alternating forward / backward scan order)."""
    fill_max_cost: float = 0.15
    """A missing pixel takes a neighbour's depth only when its cost at the pixel is below this."""
    fill_color_max: float = 0.08
    """... and when the eq. 3.4 diff to that neighbour's color is below this."""
    max_fill_hops: int = 40
    """... and when it is at most this many propagation steps away from an originally valid pixel."""
    median_radius: int = 4
    """r of the (2r+1)^2 weighted median window."""
    median_color_sigma: float = 0.06
    """Color scale of the weighted median's color weight exp(-diff^2 / (2 sigma^2))."""
    median_spatial_sigma: float = 3.0
    """Spatial scale (pixels) of the weighted median's Gaussian weight."""
    cost_sigma: float = 0.15
    """Confidence weight exp(-C / cost_sigma) of each depth in the weighted median."""
    median_min_support: float = 0.5
    """A missing pixel is filled by the median only when valid pixels carry this weight fraction."""
    sharp_refs: bool = False
    """Down-weight blurred references in C_pixel (beyond the thesis): each reference's cost counts
    with weight ``(score / best score of the references) ** sharp_refs_gamma`` (re-blur sharpness,
    :func:`presim.capture.sharpness.sharpness_score`), so a motion-blurred neighbour, whose colours
    and gradients are smeared, outvotes the sharp ones less. Set by the scene-level refinement
    (:func:`reference_weights`); :func:`refine_depth` itself uses ``RefView.weight``."""
    sharp_refs_gamma: float = 2.0
    """Exponent of the sharpness weight."""
    backend: str = "numba"
    """``"numba"`` (fast) or ``"reference"`` (slow, plain Python; tests on tiny inputs)."""

    def __post_init__(self) -> None:
        if self.patch_size < 3 or self.patch_size % 2 == 0:
            raise ValueError(f"patch_size must be odd and >= 3, got {self.patch_size}")
        if self.backend not in ("numba", "reference"):
            raise ValueError(f"backend must be 'numba' or 'reference', got {self.backend!r}")
        if not 0.0 <= self.lam <= 1.0:
            raise ValueError(f"lam must be in [0, 1], got {self.lam}")


@dataclass(frozen=True)
class RefView:
    """A reference view: its color, depth (for the front-most test), intrinsics and pose."""

    color: np.ndarray
    """uint8 (H, W, 3) RGB."""
    depth_m: np.ndarray
    """float32 (H, W) metres, 0 = invalid."""
    K: Intrinsics
    T_world_cam: np.ndarray
    """4x4 camera-to-world."""
    weight: float = 1.0
    """Weight of this reference's cost in the mean over references (C_pixel); 1 = the thesis'
    plain mean. :func:`reference_weights` gives sharpness weights."""


def reference_weights(colors: Sequence[np.ndarray], gamma: float = 2.0) -> list[float]:
    """Sharpness weights of reference images: ``(score / max score) ** gamma`` in (0, 1], the
    sharpest reference 1 (re-blur score, :func:`presim.capture.sharpness.sharpness_score`)."""

    sc = np.array([sharpness_score(c) for c in colors], dtype=np.float64)
    if len(sc) == 0:
        return []
    best = max(float(sc.max()), 1e-6)
    return [float(max(s / best, 1e-3) ** gamma) for s in sc]


@dataclass(frozen=True)
class RefinedDepth:
    """Result of :func:`refine_depth`."""

    depth_m: np.ndarray
    """float32 (H, W) refined depth, metres, 0 = still unknown."""
    cost: np.ndarray
    """float32 (H, W) matching cost C after propagation (inf where no depth)."""
    filled: np.ndarray
    """bool (H, W): no depth in the input, depth in the output."""
    changed: np.ndarray = field(repr=False)
    """bool (H, W): valid in the input and changed by more than 1 mm."""


class CostParams(NamedTuple):
    """The cost terms' parameters as the numba kernels take them (from :class:`RefineConfig`)."""

    lam: float
    """lambda of eq. 3.2 / 3.4 (color vs gradient)."""
    truncation: float
    """Per-reference cost truncation."""
    occlusion_rel_tol: float
    """Front-most test tolerance."""
    patch_weight: float
    """Weight of C_patch."""
    support_gamma: float
    """gamma of the adaptive support weight."""
    depth_rel_tol: float
    """Relative depth difference of full disagreement in C_patch."""
    half_patch: int
    """h = patch_size // 2."""
    unseen_cost: float
    """C_pixel of a depth no reference sees front-most."""


class FillParams(NamedTuple):
    """Propagation parameters as the numba kernel takes them (from :class:`RefineConfig`)."""

    fill_max_cost: float
    fill_color_max: float
    max_fill_hops: int
    num_passes: int


def _kernel_params(cfg: RefineConfig) -> tuple[CostParams, FillParams]:
    return (CostParams(float(cfg.lam), float(cfg.truncation), float(cfg.occlusion_rel_tol),
                       float(cfg.patch_weight), float(cfg.support_gamma), float(cfg.depth_rel_tol),
                       int(cfg.patch_size // 2), float(cfg.unseen_cost)),
            FillParams(float(cfg.fill_max_cost), float(cfg.fill_color_max), int(cfg.max_fill_hops),
                       int(cfg.num_passes)))


# ---- preprocessing (shared by both backends) -----------------------------------------------------

def prepare_image(color: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Color uint8 (H,W,3) -> (float64 (H,W,3) in [0,1], gray gradients float64 (H,W,2))."""
    img = color.astype(np.float64) / 255.0
    gray = img.mean(axis=2)
    p = np.pad(gray, 1, mode="edge")
    gx = 0.5 * (p[1:-1, 2:] - p[1:-1, :-2])
    gy = 0.5 * (p[2:, 1:-1] - p[:-2, 1:-1])
    return img, np.stack([gx, gy], axis=-1)


def select_reference_views(T_world_cams: np.ndarray, target_idx: int, candidates: Sequence[int],
                           num_refs: int = 10, max_angle_deg: float = 60.0) -> list[int]:
    """Reference frames for ``target_idx`` (thesis: chosen by distance and angle): among
    ``candidates`` (positions into ``T_world_cams``), those whose optical axis is within
    ``max_angle_deg`` of the target's, nearest camera centre first; at most ``num_refs``."""
    T = np.asarray(T_world_cams, dtype=np.float64)
    c_t, z_t = T[target_idx, :3, 3], T[target_idx, :3, 2]
    cand = np.array([int(c) for c in candidates if int(c) != int(target_idx)], dtype=np.int64)
    if len(cand) == 0:
        return []
    cos = T[cand, :3, 2] @ z_t
    ok = cos >= np.cos(np.radians(max_angle_deg))
    cand = cand[ok]
    dist = np.linalg.norm(T[cand, :3, 3] - c_t, axis=1)
    return [int(i) for i in cand[np.argsort(dist, kind="stable")][:num_refs]]


def _check_inputs(color, depth_m, K: Intrinsics, T_world_cam, ref_views) -> None:
    H, W = K.height, K.width
    if color.shape != (H, W, 3) or color.dtype != np.uint8:
        raise ValueError(f"refine_depth: color must be uint8 ({H},{W},3), got {color.dtype} {color.shape}")
    if depth_m.shape != (H, W):
        raise ValueError(f"refine_depth: depth must be ({H},{W}), got {depth_m.shape}")
    if np.asarray(T_world_cam).shape != (4, 4):
        raise ValueError("refine_depth: T_world_cam must be 4x4")
    for i, r in enumerate(ref_views):
        h, w = r.K.height, r.K.width
        if r.color.shape != (h, w, 3) or r.depth_m.shape != (h, w):
            raise ValueError(f"refine_depth: reference {i} color/depth do not match its intrinsics {w}x{h}")
        if (h, w) != (ref_views[0].K.height, ref_views[0].K.width):
            raise ValueError("refine_depth: all reference views must share one resolution")


# ---- numba kernels -----------------------------------------------------------------------------

@nb.njit(cache=True, fastmath=False)
def _pixel_cost_nb(u, v, d, fx, fy, cx, cy, img_t, grad_t, R_rt, t_rt, kr, img_r, grad_r, dep_r,
                   lam, trunc, occ_tol, unseen):
    x = (u - cx) / fx * d
    y = (v - cy) / fy * d
    # kr[r] = (fx, fy, cx, cy, weight) of reference r; the cost is the weighted mean over references.
    acc = 0.0
    n = 0.0
    Hr = img_r.shape[1]
    Wr = img_r.shape[2]
    for r in range(R_rt.shape[0]):
        px = R_rt[r, 0, 0] * x + R_rt[r, 0, 1] * y + R_rt[r, 0, 2] * d + t_rt[r, 0]
        py = R_rt[r, 1, 0] * x + R_rt[r, 1, 1] * y + R_rt[r, 1, 2] * d + t_rt[r, 1]
        pz = R_rt[r, 2, 0] * x + R_rt[r, 2, 1] * y + R_rt[r, 2, 2] * d + t_rt[r, 2]
        if pz <= 1e-6:
            continue
        iu = int(np.floor(kr[r, 0] * px / pz + kr[r, 2] + 0.5))
        iv = int(np.floor(kr[r, 1] * py / pz + kr[r, 3] + 0.5))
        if iu < 0 or iv < 0 or iu >= Wr or iv >= Hr:
            continue
        dr = dep_r[r, iv, iu]
        if dr > 0.0 and pz > dr * (1.0 + occ_tol):
            continue  # not front-most: the reference sees a surface in front of this point
        cc = (abs(img_t[v, u, 0] - img_r[r, iv, iu, 0]) + abs(img_t[v, u, 1] - img_r[r, iv, iu, 1])
              + abs(img_t[v, u, 2] - img_r[r, iv, iu, 2])) / 3.0
        cg = (abs(grad_t[v, u, 0] - grad_r[r, iv, iu, 0]) + abs(grad_t[v, u, 1] - grad_r[r, iv, iu, 1])) / 2.0
        c = lam * cc + (1.0 - lam) * cg
        if c > trunc:
            c = trunc
        acc += kr[r, 4] * c
        n += kr[r, 4]
    if n <= 0.0:
        return unseen
    return acc / n


@nb.njit(cache=True)
def _diff_nb(img, grad, v0, u0, v1, u1, lam):
    cc = (abs(img[v0, u0, 0] - img[v1, u1, 0]) + abs(img[v0, u0, 1] - img[v1, u1, 1])
          + abs(img[v0, u0, 2] - img[v1, u1, 2])) / 3.0
    cg = (abs(grad[v0, u0, 0] - grad[v1, u1, 0]) + abs(grad[v0, u0, 1] - grad[v1, u1, 1])) / 2.0
    return lam * cc + (1.0 - lam) * cg


@nb.njit(cache=True, parallel=True)
def _support_nb(img, grad, h, lam, gamma):
    # Per pixel and patch offset: the eq. 3.4 diff and the support weight exp(-diff / gamma). They do
    # not depend on depth, so they are computed once instead of in every cost evaluation.
    H, W = img.shape[0], img.shape[1]
    n = 2 * h + 1
    dif = np.full((H, W, n * n), np.inf)
    sup = np.zeros((H, W, n * n))
    for v in nb.prange(H):
        for u in range(W):
            k = 0
            for dy in range(-h, h + 1):
                for dx in range(-h, h + 1):
                    qv = v + dy
                    qu = u + dx
                    if qv >= 0 and qu >= 0 and qv < H and qu < W:
                        df = _diff_nb(img, grad, v, u, qv, qu, lam)
                        dif[v, u, k] = df
                        sup[v, u, k] = np.exp(-df / gamma)
                    k += 1
    return dif, sup


@nb.njit(cache=True)
def _patch_cost_nb(u, v, d, D, sup, h, rel_tol):
    H, W = D.shape
    sw = 0.0
    acc = 0.0
    k = -1
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            k += 1
            if dy == 0 and dx == 0:
                continue
            qv = v + dy
            qu = u + dx
            if qv < 0 or qu < 0 or qv >= H or qu >= W:
                continue
            dq = D[qv, qu]
            if dq <= 0.0:
                continue
            w = sup[v, u, k]
            e = abs(d - dq) / (rel_tol * d)
            if e > 1.0:
                e = 1.0
            acc += w * e
            sw += w
    if sw <= 0.0:
        return 0.5
    return acc / sw


@nb.njit(cache=True)
def _cost_nb(u, v, d, D, fx, fy, cx, cy, img, grad, sup, R_rt, t_rt, kr, img_r, grad_r, dep_r, p):
    # p: CostParams
    cp = _pixel_cost_nb(u, v, d, fx, fy, cx, cy, img, grad, R_rt, t_rt, kr, img_r, grad_r, dep_r,
                        p.lam, p.truncation, p.occlusion_rel_tol, p.unseen_cost)
    return cp + p.patch_weight * _patch_cost_nb(u, v, d, D, sup, p.half_patch, p.depth_rel_tol)


@nb.njit(cache=True, parallel=True)
def _initial_cost_nb(D, fx, fy, cx, cy, img, grad, sup, R_rt, t_rt, kr, img_r, grad_r, dep_r, p):
    H, W = D.shape
    C = np.full((H, W), np.inf)
    for v in nb.prange(H):
        for u in range(W):
            if D[v, u] > 0.0:
                C[v, u] = _cost_nb(u, v, D[v, u], D, fx, fy, cx, cy, img, grad, sup, R_rt, t_rt, kr,
                                   img_r, grad_r, dep_r, p)
    return C


@nb.njit(cache=True)
def _propagate_nb(D, C, hops, fx, fy, cx, cy, img, grad, sup, dif, R_rt, t_rt, kr, img_r, grad_r,
                  dep_r, p, q):
    # p: CostParams, q: FillParams
    H, W = D.shape
    h = p.half_patch
    for it in range(q.num_passes):
        fwd = it % 2 == 0
        for vi in range(H):
            v = vi if fwd else H - 1 - vi
            for ui in range(W):
                u = ui if fwd else W - 1 - ui
                invalid = D[v, u] <= 0.0
                if not invalid:
                    s = 0.0
                    n = 0
                    for dy in range(-h, h + 1):
                        for dx in range(-h, h + 1):
                            qv = v + dy
                            qu = u + dx
                            if qv < 0 or qu < 0 or qv >= H or qu >= W:
                                continue
                            if np.isfinite(C[qv, qu]):
                                s += C[qv, qu]
                                n += 1
                    if C[v, u] <= s / n:
                        continue
                best_d = D[v, u]
                best_c = C[v, u]
                best_h = hops[v, u]
                k = -1
                for dy in range(-h, h + 1):
                    for dx in range(-h, h + 1):
                        k += 1
                        if dy == 0 and dx == 0:
                            continue
                        qv = v + dy
                        qu = u + dx
                        if qv < 0 or qu < 0 or qv >= H or qu >= W:
                            continue
                        dq = D[qv, qu]
                        if dq <= 0.0 or dq == best_d:
                            continue
                        if invalid:
                            if hops[qv, qu] >= q.max_fill_hops:
                                continue
                            if dif[v, u, k] > q.fill_color_max:
                                continue
                        c = _cost_nb(u, v, dq, D, fx, fy, cx, cy, img, grad, sup, R_rt, t_rt, kr, img_r,
                                     grad_r, dep_r, p)
                        if c < best_c:
                            best_c = c
                            best_d = dq
                            best_h = hops[qv, qu] + 1 if invalid else hops[v, u]
                if invalid and best_c >= q.fill_max_cost:
                    continue
                D[v, u] = best_d
                C[v, u] = best_c
                hops[v, u] = best_h


@nb.njit(cache=True, parallel=True)
def _weighted_median_nb(D, C, img, grad, r, lam, csig, ssig, costsig, min_support):
    H, W = D.shape
    out = np.zeros((H, W), np.float32)
    nmax = (2 * r + 1) * (2 * r + 1)
    spatial = np.empty(nmax)
    k = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            spatial[k] = np.exp(-(dx * dx + dy * dy) / (2.0 * ssig * ssig))
            k += 1
    conf = np.zeros((H, W))
    for v in nb.prange(H):
        for u in range(W):
            if D[v, u] > 0.0:
                conf[v, u] = np.exp(-C[v, u] / costsig)
    inv2c = 1.0 / (2.0 * csig * csig)
    for v in nb.prange(H):
        vals = np.empty(nmax)
        ws = np.empty(nmax)
        for u in range(W):
            n = 0
            wall = 0.0
            wvalid = 0.0
            tot = 0.0
            k = -1
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    k += 1
                    qv = v + dy
                    qu = u + dx
                    if qv < 0 or qu < 0 or qv >= H or qu >= W:
                        continue
                    df = _diff_nb(img, grad, v, u, qv, qu, lam)
                    w = np.exp(-df * df * inv2c) * spatial[k]
                    wall += w
                    if D[qv, qu] > 0.0:
                        wvalid += w
                        x = D[qv, qu]
                        wx = w * conf[qv, qu]
                        tot += wx
                        # insertion into the sorted prefix (stable: equal values keep window order)
                        j = n
                        while j > 0 and vals[j - 1] > x:
                            vals[j] = vals[j - 1]
                            ws[j] = ws[j - 1]
                            j -= 1
                        vals[j] = x
                        ws[j] = wx
                        n += 1
            if n == 0:
                continue
            if D[v, u] <= 0.0 and wvalid < min_support * wall:
                continue
            if tot <= 0.0:
                continue
            cum = 0.0
            for j in range(n):
                cum += ws[j]
                if cum >= 0.5 * tot:
                    out[v, u] = vals[j]
                    break
    return out


# ---- reference implementation (slow, plain; same order of operations) ------------------------------

def _ref_pixel_cost(u, v, d, K: Intrinsics, img, grad, refs, cfg: RefineConfig) -> float:
    X = np.array([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, d])
    costs = []
    for (R, t, Kr, img_r, grad_r, dep_r, w) in refs:
        P = R @ X + t
        if P[2] <= 1e-6:
            continue
        iu = int(np.floor(Kr.fx * P[0] / P[2] + Kr.cx + 0.5))
        iv = int(np.floor(Kr.fy * P[1] / P[2] + Kr.cy + 0.5))
        if not (0 <= iu < Kr.width and 0 <= iv < Kr.height):
            continue
        if dep_r[iv, iu] > 0 and P[2] > dep_r[iv, iu] * (1.0 + cfg.occlusion_rel_tol):
            continue
        cc = np.abs(img[v, u] - img_r[iv, iu]).sum() / 3.0
        cg = np.abs(grad[v, u] - grad_r[iv, iu]).sum() / 2.0
        costs.append((min(cfg.lam * cc + (1 - cfg.lam) * cg, cfg.truncation), w))
    acc = wsum = 0.0
    for c, w in costs:
        acc += w * c
        wsum += w
    if wsum <= 0.0:
        return cfg.unseen_cost
    return acc / wsum


def _ref_diff(img, grad, a, b, lam) -> float:
    cc = np.abs(img[a] - img[b]).sum() / 3.0
    cg = np.abs(grad[a] - grad[b]).sum() / 2.0
    return lam * cc + (1 - lam) * cg


def _ref_cost(u, v, d, D, K, img, grad, refs, cfg: RefineConfig) -> float:
    H, W = D.shape
    h = cfg.patch_size // 2
    acc = sw = 0.0
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            qv, qu = v + dy, u + dx
            if (dy, dx) == (0, 0) or not (0 <= qv < H and 0 <= qu < W) or D[qv, qu] <= 0:
                continue
            w = np.exp(-_ref_diff(img, grad, (v, u), (qv, qu), cfg.lam) / cfg.support_gamma)
            acc += w * min(abs(d - D[qv, qu]) / (cfg.depth_rel_tol * d), 1.0)
            sw += w
    patch = acc / sw if sw > 0 else 0.5
    return _ref_pixel_cost(u, v, d, K, img, grad, refs, cfg) + cfg.patch_weight * patch


def _ref_refine(D, K, img, grad, refs, cfg: RefineConfig):
    H, W = D.shape
    h = cfg.patch_size // 2
    C = np.full((H, W), np.inf)
    for v in range(H):
        for u in range(W):
            if D[v, u] > 0:
                C[v, u] = _ref_cost(u, v, D[v, u], D, K, img, grad, refs, cfg)
    hops = np.zeros((H, W), np.int32)
    for it in range(cfg.num_passes):
        rows = range(H) if it % 2 == 0 else range(H - 1, -1, -1)
        for v in rows:
            cols = range(W) if it % 2 == 0 else range(W - 1, -1, -1)
            for u in cols:
                invalid = D[v, u] <= 0
                if not invalid:
                    patch = [C[qv, qu] for qv in range(v - h, v + h + 1) for qu in range(u - h, u + h + 1)
                             if 0 <= qv < H and 0 <= qu < W and np.isfinite(C[qv, qu])]
                    if C[v, u] <= sum(patch) / len(patch):
                        continue
                best = (C[v, u], D[v, u], hops[v, u])
                for dy in range(-h, h + 1):
                    for dx in range(-h, h + 1):
                        qv, qu = v + dy, u + dx
                        if (dy, dx) == (0, 0) or not (0 <= qv < H and 0 <= qu < W):
                            continue
                        dq = D[qv, qu]
                        if dq <= 0 or dq == best[1]:
                            continue
                        if invalid and (hops[qv, qu] >= cfg.max_fill_hops or
                                        _ref_diff(img, grad, (v, u), (qv, qu), cfg.lam) > cfg.fill_color_max):
                            continue
                        c = _ref_cost(u, v, dq, D, K, img, grad, refs, cfg)
                        if c < best[0]:
                            best = (c, dq, hops[qv, qu] + 1 if invalid else hops[v, u])
                if invalid and best[0] >= cfg.fill_max_cost:
                    continue
                C[v, u], D[v, u], hops[v, u] = best
    # weighted median
    r = cfg.median_radius
    out = np.zeros((H, W), np.float32)
    for v in range(H):
        for u in range(W):
            vals, ws = [], []
            wall = wvalid = 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    qv, qu = v + dy, u + dx
                    if not (0 <= qv < H and 0 <= qu < W):
                        continue
                    df = _ref_diff(img, grad, (v, u), (qv, qu), cfg.lam)
                    w = np.exp(-df * df / (2 * cfg.median_color_sigma ** 2)
                               - (dx * dx + dy * dy) / (2 * cfg.median_spatial_sigma ** 2))
                    wall += w
                    if D[qv, qu] > 0:
                        wvalid += w
                        vals.append(D[qv, qu])
                        ws.append(w * np.exp(-C[qv, qu] / cfg.cost_sigma))
            if not vals or (D[v, u] <= 0 and wvalid < cfg.median_min_support * wall):
                continue
            order = np.argsort(np.array(vals), kind="mergesort")
            tot = sum(ws)
            if tot <= 0:
                continue
            cum = 0.0
            for k in order:
                cum += ws[k]
                if cum >= 0.5 * tot:
                    out[v, u] = vals[k]
                    break
    return out, C


# ---- public entry ------------------------------------------------------------------------------

def refine_depth(color: np.ndarray, depth_m: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                 ref_views: Sequence[RefView], config: RefineConfig = RefineConfig()) -> RefinedDepth:
    """Refine one depth map against reference views (thesis §3.4.1, Alg. 1). Pure function.

    Args:
        color: uint8 (H, W, 3) RGB of the target frame.
        depth_m: float32 (H, W) raw z-depth in metres, 0 = invalid.
        K: intrinsics of the target (H = K.height, W = K.width).
        T_world_cam: 4x4 camera-to-world pose of the target.
        ref_views: reference views (the thesis uses 10; see :func:`select_reference_views`).
        config: :class:`RefineConfig`.

    Returns:
        :class:`RefinedDepth` with the refined depth (0 where still unknown), the matching cost and
        masks of filled / changed pixels.

    Example:
        >>> out = refine_depth(f.color, f.depth_m, f.K, f.T_world_cam, refs)  # doctest: +SKIP
    """
    color = np.asarray(color)
    depth_in = np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    depth_in[depth_in < 0] = 0
    _check_inputs(color, depth_in, K, T_world_cam, ref_views)
    cfg = config
    img, grad = prepare_image(color)
    D = depth_in.astype(np.float64)

    if cfg.backend == "reference":
        refs = []
        for r in ref_views:
            T_rt = compose(invert(r.T_world_cam), np.asarray(T_world_cam, dtype=np.float64))
            ir, gr = prepare_image(np.asarray(r.color))
            refs.append((T_rt[:3, :3], T_rt[:3, 3], r.K, ir, gr, np.asarray(r.depth_m, dtype=np.float64),
                         float(r.weight)))
        out, C = _ref_refine(D, K, img, grad, refs, cfg)
    else:
        R_n = len(ref_views)
        if R_n:
            Hr, Wr = ref_views[0].K.height, ref_views[0].K.width
        else:
            Hr, Wr = 1, 1
        img_r = np.zeros((R_n, Hr, Wr, 3))
        grad_r = np.zeros((R_n, Hr, Wr, 2))
        dep_r = np.zeros((R_n, Hr, Wr))
        R_rt = np.zeros((R_n, 3, 3))
        t_rt = np.zeros((R_n, 3))
        kr = np.zeros((R_n, 5))
        for i, r in enumerate(ref_views):
            T_rt = compose(invert(r.T_world_cam), np.asarray(T_world_cam, dtype=np.float64))
            R_rt[i], t_rt[i] = T_rt[:3, :3], T_rt[:3, 3]
            kr[i] = (r.K.fx, r.K.fy, r.K.cx, r.K.cy, float(r.weight))
            img_r[i], grad_r[i] = prepare_image(np.asarray(r.color))
            dep_r[i] = np.asarray(r.depth_m, dtype=np.float64)
        p, q = _kernel_params(cfg)
        dif, sup = _support_nb(img, grad, cfg.patch_size // 2, cfg.lam, cfg.support_gamma)
        C = _initial_cost_nb(D, K.fx, K.fy, K.cx, K.cy, img, grad, sup, R_rt, t_rt, kr, img_r, grad_r, dep_r, p)
        hops = np.zeros(D.shape, np.int64)
        _propagate_nb(D, C, hops, K.fx, K.fy, K.cx, K.cy, img, grad, sup, dif, R_rt, t_rt, kr,
                      img_r, grad_r, dep_r, p, q)
        out = _weighted_median_nb(D, C, img, grad, cfg.median_radius, cfg.lam, cfg.median_color_sigma,
                                  cfg.median_spatial_sigma, cfg.cost_sigma, cfg.median_min_support)
    valid_in = depth_in > 0
    return RefinedDepth(
        depth_m=out.astype(np.float32),
        cost=C.astype(np.float32),
        filled=(~valid_in) & (out > 0),
        changed=valid_in & (np.abs(out - depth_in) > 1e-3),
    )
