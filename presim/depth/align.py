"""Depth-to-colour alignment (thesis §5.3.4.1, Algorithm 2).

The captured (sensor) depth of a frame is often shifted against its colour image by a few pixels
(unregistered or badly registered sensors, stereo matching near edges), while the *estimated* depth
(here: the scene's refined depth, ``presim refine``, whose edges follow the colour edges) sits on the
colour image. :func:`align_depth` moves the captured depth onto the estimated one with a per-pixel
offset map found by PatchMatch-style propagation:

1. **Scale** (Alg. 2 line 1): the metric scale ``s`` with ``D_c ~ s * D_e`` by a RANSAC fit of a line
   through the origin on pixels valid in both (refit: median ratio of the inliers) (``fit_scale``); the estimate is scaled by ``s`` before
   any comparison. Our estimates are metric already, so ``s`` is ~1 there; the step matters for an
   up-to-scale MVS estimate as in the thesis.
2. **Normals** (eq. 5.3-5.4) of both depth maps from the unprojected points: the cross product of
   the central differences over ``normal_step_px`` (the least-squares plane of the 4-neighbour
   stencil). A normal is *unknown* across a depth jump (``> normal_max_jump_rel``) or a hole.
3. **Offset map** ``O`` (H, W, 2) on the colour/estimate grid, initialised to 0 (the sensor's own
   registration is the prior). Pixel ``q`` of the estimate is matched to pixel ``p = q + O[q]`` of
   the captured depth. *Choice*: the thesis defines offsets on the captured patch and maps it onto
   the estimate; defining them on the estimate's grid makes the final mapping a gather
   ``D_c1[q] = D_c[q + O[q]]`` (no collisions, no holes from the mapping itself).
4. **Matching cost** of an offset ``o`` at ``q`` (Alg. 2 line 7): ``rel = |D_c[p] - s D_e[q]| / (s D_e[q])``;
   ``0`` when ``rel <= agree_rel`` (agreement within sensor noise: no reason to move), else
   ``rel - agree_rel`` (capped at ``unmatched_cost``) if the angle between the normals of ``p`` and
   ``q`` is below ``max_normal_angle_deg`` or either normal is unknown, else ``unmatched_cost`` (the
   thesis keeps ``dd_i`` only when the normal test passes). A ``p`` outside the image or without
   captured depth costs ``unmatched_cost``. Each offset adds ``offset_penalty`` per pixel of its L1
   length, so among equally good offsets the shortest wins and flat regions keep ``O = 0``.
5. **Propagation** (Alg. 2 line 8): passes in scan order, alternating forward (from the top left)
   and backward. At ``q`` the candidates are its own offset and the offsets of the two neighbours
   already visited in this pass, each also moved by one pixel in x or y (so an offset grows by
   one pixel per step along the scan and a k-pixel shift is found within one pass in the right
   direction); a candidate replaces the current offset only when its cost is strictly lower and
   it stays within ``max_offset_px`` per axis. After each pass the sum of the costs ``c_i`` is
   taken; the passes stop when it changes by at most ``stop_rel`` (relative) or after ``max_passes``.
6. **Mapping** (Alg. 2 line 9): ``D_c1[q] = D_c[q + O[q]]``. Only pixels with both a captured and
   an estimated depth are matched: where the estimate has none, ``O = 0`` and ``D_c1 = D_c``; where
   the sensor has none, ``O = 0`` and ``D_c1 = 0`` (the alignment moves measurements, it never
   invents them: filling holes is the fusion's job, :mod:`presim.depth.fuse`).

Two implementations: a numba fast path (default) and a plain Python reference
(``backend="reference"``) with the same order of operations; tests check they agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba as nb
import numpy as np

from presim.geometry import Intrinsics

__all__ = ["AlignConfig", "AlignedDepth", "align_depth", "fit_scale_ransac", "depth_normals"]


@dataclass(frozen=True)
class AlignConfig:
    """Parameters of :func:`align_depth` (the thesis gives no values; ours are documented here)."""

    fit_scale: bool = True
    """Fit the metric scale of the estimate by RANSAC (Alg. 2 line 1); False = scale 1."""
    ransac_iters: int = 200
    """RANSAC hypotheses (one pixel each: a line through the origin has one parameter)."""
    ransac_samples: int = 20000
    """Pixels (valid in both) drawn for the RANSAC fit."""
    ransac_inlier_rel: float = 0.02
    """A pixel is an inlier of scale s when ``|D_c - s D_e| <= this * D_c``."""
    agree_rel: float = 0.02
    """Relative depth difference below which a match costs 0 (sensor noise; no reason to move)."""
    max_normal_angle_deg: float = 30.0
    """A match whose normals differ more than this (both known) costs ``unmatched_cost``."""
    normal_step_px: int = 2
    """Half-width (pixels) of the central differences the normals are computed from."""
    normal_max_jump_rel: float = 0.05
    """A normal is unknown where a stencil neighbour's depth differs by more than this (relative)."""
    unmatched_cost: float = 1.0
    """Cost of a match without captured depth, outside the image or failing the normal test."""
    offset_penalty: float = 0.002
    """Cost per pixel of an offset's L1 length (prefers short offsets among equal matches)."""
    max_offset_px: int = 8
    """Largest offset per axis (pixels)."""
    max_passes: int = 8
    """Most propagation passes."""
    stop_rel: float = 1e-3
    """Stop when the cost sum changes by at most this fraction of the previous sum."""
    seed: int = 0
    """Seed of the RANSAC sampling (deterministic results)."""
    backend: str = "numba"
    """``"numba"`` (fast) or ``"reference"`` (slow, plain Python; tests on tiny inputs)."""

    def __post_init__(self) -> None:
        if self.backend not in ("numba", "reference"):
            raise ValueError(f"backend must be 'numba' or 'reference', got {self.backend!r}")
        if self.max_offset_px < 0 or self.max_passes < 1 or self.normal_step_px < 1:
            raise ValueError("max_offset_px must be >= 0, max_passes >= 1 and normal_step_px >= 1")


@dataclass(frozen=True)
class AlignedDepth:
    """Result of :func:`align_depth`."""

    depth_m: np.ndarray
    """float32 (H, W): captured depth mapped onto the colour grid, ``D_c[q + O[q]]`` (0 = none)."""
    offsets: np.ndarray
    """int32 (H, W, 2): offset map ``O`` as (dx, dy) pixels from colour pixel to captured pixel."""
    cost: np.ndarray = field(repr=False)
    """float32 (H, W): matching cost at the final offset (0 where either depth is missing)."""
    scale: float = 1.0
    """Metric scale s of the estimate (``D_c ~ s D_e``)."""
    cost_sums: tuple[float, ...] = ()
    """Cost sum c_i before the first pass and after each pass."""


# ---- scale and normals (shared by both backends) ---------------------------------------------------

def fit_scale_ransac(captured_m: np.ndarray, estimated_m: np.ndarray, config: AlignConfig = AlignConfig()) -> float:
    """Scale ``s`` with ``captured ~ s * estimated`` (RANSAC over single-pixel hypotheses, then the
    median ratio of the best hypothesis' inliers, which outliers inside the band barely move). 1.0
    when fewer than 10 pixels are valid in both."""
    m = (captured_m > 0) & (estimated_m > 0)
    c = captured_m[m].astype(np.float64)
    e = estimated_m[m].astype(np.float64)
    if len(c) < 10:
        return 1.0
    rng = np.random.default_rng(config.seed)
    if len(c) > config.ransac_samples:
        pick = rng.choice(len(c), config.ransac_samples, replace=False)
        c, e = c[pick], e[pick]
    hyp = rng.integers(0, len(c), config.ransac_iters)
    best_n, best_in = -1, None
    for h in hyp:
        s = c[h] / e[h]
        inl = np.abs(c - s * e) <= config.ransac_inlier_rel * c
        n = int(inl.sum())
        if n > best_n:
            best_n, best_in = n, inl
    return float(np.median(c[best_in] / e[best_in]))


@nb.njit(cache=True)
def _normals_nb(D, fx, fy, cx, cy, step, jump):
    H, W = D.shape
    N = np.zeros((H, W, 3))
    for v in range(H):
        for u in range(W):
            d = D[v, u]
            if d <= 0.0 or u - step < 0 or u + step >= W or v - step < 0 or v + step >= H:
                continue
            dl = D[v, u - step]
            dr = D[v, u + step]
            du = D[v - step, u]
            dd = D[v + step, u]
            if (dl <= 0.0 or dr <= 0.0 or du <= 0.0 or dd <= 0.0 or abs(dl - d) > jump * d
                    or abs(dr - d) > jump * d or abs(du - d) > jump * d or abs(dd - d) > jump * d):
                continue
            # Points of the four stencil neighbours; tangents = central differences.
            ax = (u + step - cx) / fx * dr - (u - step - cx) / fx * dl
            ay = (v - cy) / fy * dr - (v - cy) / fy * dl
            az = dr - dl
            bx = (u - cx) / fx * dd - (u - cx) / fx * du
            by = (v + step - cy) / fy * dd - (v - step - cy) / fy * du
            bz = dd - du
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            n = np.sqrt(nx * nx + ny * ny + nz * nz)
            if n <= 0.0:
                continue
            N[v, u, 0] = nx / n
            N[v, u, 1] = ny / n
            N[v, u, 2] = nz / n
    return N


def depth_normals(depth_m: np.ndarray, K: Intrinsics, step_px: int = 2, max_jump_rel: float = 0.05) -> np.ndarray:
    """Unit normals (float64 (H, W, 3), camera frame; zero = unknown) of a depth map from the cross
    product of the central differences of its unprojected points over ``step_px``."""
    D = np.ascontiguousarray(depth_m, dtype=np.float64)
    return _normals_nb(D, float(K.fx), float(K.fy), float(K.cx), float(K.cy), int(step_px), float(max_jump_rel))


# ---- numba kernels -----------------------------------------------------------------------------------

@nb.njit(cache=True)
def _match_cost_nb(Dc, De, Nc, Ne, v, u, ox, oy, agree, cos_max, unmatched, pen):
    H, W = Dc.shape
    pv = v + oy
    pu = u + ox
    c = unmatched
    if pv >= 0 and pu >= 0 and pv < H and pu < W and Dc[pv, pu] > 0.0:
        e = De[v, u]
        rel = abs(Dc[pv, pu] - e) / e
        if rel <= agree:
            c = 0.0
        else:
            dot = Nc[pv, pu, 0] * Ne[v, u, 0] + Nc[pv, pu, 1] * Ne[v, u, 1] + Nc[pv, pu, 2] * Ne[v, u, 2]
            known = ((Nc[pv, pu, 0] != 0.0 or Nc[pv, pu, 1] != 0.0 or Nc[pv, pu, 2] != 0.0)
                     and (Ne[v, u, 0] != 0.0 or Ne[v, u, 1] != 0.0 or Ne[v, u, 2] != 0.0))
            if known and dot < cos_max:
                c = unmatched
            else:
                c = min(rel - agree, unmatched)
    return c + pen * (abs(ox) + abs(oy))


@nb.njit(cache=True)
def _align_nb(Dc, De, Nc, Ne, agree, cos_max, unmatched, pen, max_off, max_passes, stop_rel):
    H, W = Dc.shape
    O = np.zeros((H, W, 2), np.int64)
    C = np.zeros((H, W))
    total = 0.0
    for v in range(H):
        for u in range(W):
            if De[v, u] > 0.0 and Dc[v, u] > 0.0:
                C[v, u] = _match_cost_nb(Dc, De, Nc, Ne, v, u, 0, 0, agree, cos_max, unmatched, pen)
                total += C[v, u]
    sums = np.zeros(max_passes + 1)
    sums[0] = total
    done = 0
    steps = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
    for it in range(max_passes):
        fwd = it % 2 == 0
        sgn = -1 if fwd else 1  # neighbours already visited in this pass: left/up (fwd), right/down
        for vi in range(H):
            v = vi if fwd else H - 1 - vi
            for ui in range(W):
                u = ui if fwd else W - 1 - ui
                if De[v, u] <= 0.0 or Dc[v, u] <= 0.0:
                    continue
                bc = C[v, u]
                if bc <= 0.0:
                    continue  # a perfect match (cost 0 at offset 0): no candidate can be lower
                bx = O[v, u, 0]
                by = O[v, u, 1]
                for k in range(3):
                    if k == 0:
                        sx = O[v, u, 0]
                        sy = O[v, u, 1]
                    elif k == 1:
                        nu = u + sgn
                        if nu < 0 or nu >= W:
                            continue
                        sx = O[v, nu, 0]
                        sy = O[v, nu, 1]
                    else:
                        nv = v + sgn
                        if nv < 0 or nv >= H:
                            continue
                        sx = O[nv, u, 0]
                        sy = O[nv, u, 1]
                    for s in range(5):
                        cx = sx + steps[s][0]
                        cy = sy + steps[s][1]
                        if abs(cx) > max_off or abs(cy) > max_off or (cx == bx and cy == by):
                            continue
                        c = _match_cost_nb(Dc, De, Nc, Ne, v, u, cx, cy, agree, cos_max, unmatched, pen)
                        if c < bc:
                            bc = c
                            bx = cx
                            by = cy
                C[v, u] = bc
                O[v, u, 0] = bx
                O[v, u, 1] = by
        prev = total
        total = 0.0
        for v in range(H):
            for u in range(W):
                total += C[v, u]
        sums[it + 1] = total
        done = it + 1
        if abs(prev - total) <= stop_rel * prev:
            break
    return O, C, sums[:done + 1]


# ---- reference implementation (slow, plain; same order of operations) ---------------------------------

def _ref_match_cost(Dc, De, Nc, Ne, v, u, ox, oy, cfg: AlignConfig) -> float:
    H, W = Dc.shape
    pv, pu = v + oy, u + ox
    c = cfg.unmatched_cost
    if 0 <= pv < H and 0 <= pu < W and Dc[pv, pu] > 0:
        rel = abs(Dc[pv, pu] - De[v, u]) / De[v, u]
        if rel <= cfg.agree_rel:
            c = 0.0
        else:
            known = bool(np.any(Nc[pv, pu] != 0) and np.any(Ne[v, u] != 0))
            angle_deg = np.degrees(np.arccos(np.clip(float(Nc[pv, pu] @ Ne[v, u]), -1.0, 1.0)))
            c = cfg.unmatched_cost if known and angle_deg > cfg.max_normal_angle_deg else min(rel - cfg.agree_rel, cfg.unmatched_cost)
    return c + cfg.offset_penalty * (abs(ox) + abs(oy))


def _ref_align(Dc, De, Nc, Ne, cfg: AlignConfig):
    H, W = Dc.shape
    O = np.zeros((H, W, 2), np.int64)
    C = np.zeros((H, W))
    for v in range(H):
        for u in range(W):
            if De[v, u] > 0 and Dc[v, u] > 0:
                C[v, u] = _ref_match_cost(Dc, De, Nc, Ne, v, u, 0, 0, cfg)
    sums = [float(C.sum())]
    for it in range(cfg.max_passes):
        fwd = it % 2 == 0
        sgn = -1 if fwd else 1
        for v in (range(H) if fwd else range(H - 1, -1, -1)):
            for u in (range(W) if fwd else range(W - 1, -1, -1)):
                if De[v, u] <= 0 or Dc[v, u] <= 0:
                    continue
                best = (C[v, u], int(O[v, u, 0]), int(O[v, u, 1]))
                if best[0] <= 0:
                    continue
                seeds = [(int(O[v, u, 0]), int(O[v, u, 1]))]
                if 0 <= u + sgn < W:
                    seeds.append((int(O[v, u + sgn, 0]), int(O[v, u + sgn, 1])))
                if 0 <= v + sgn < H:
                    seeds.append((int(O[v + sgn, u, 0]), int(O[v + sgn, u, 1])))
                for sx, sy in seeds:
                    for dx, dy in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
                        cx, cy = sx + dx, sy + dy
                        if max(abs(cx), abs(cy)) > cfg.max_offset_px or (cx, cy) == best[1:]:
                            continue
                        c = _ref_match_cost(Dc, De, Nc, Ne, v, u, cx, cy, cfg)
                        if c < best[0]:
                            best = (c, cx, cy)
                C[v, u], O[v, u, 0], O[v, u, 1] = best
        sums.append(float(sum(C[v, u] for v in range(H) for u in range(W))))
        if abs(sums[-2] - sums[-1]) <= cfg.stop_rel * sums[-2]:
            break
    return O, C, np.array(sums)


# ---- public entry ------------------------------------------------------------------------------------

def align_depth(captured_m: np.ndarray, estimated_m: np.ndarray, K: Intrinsics,
                config: AlignConfig = AlignConfig()) -> AlignedDepth:
    """Align a captured depth map to the estimated depth of the same colour frame (thesis §5.3.4.1,
    Alg. 2; see the module docstring). Pure function.

    Args:
        captured_m: float32 (H, W) sensor z-depth in metres, 0 = invalid.
        estimated_m: float32 (H, W) estimated depth of the colour image (e.g. the refined depth), 0 = none.
        K: intrinsics of the colour image (both maps are on its pixel grid).
        config: :class:`AlignConfig`.

    Returns:
        :class:`AlignedDepth`: the captured depth gathered through the offset map, the offsets, the
        final matching cost, the fitted scale and the cost sums per pass.
    """
    Dc = np.nan_to_num(np.asarray(captured_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    De = np.nan_to_num(np.asarray(estimated_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if Dc.shape != (K.height, K.width) or De.shape != Dc.shape:
        raise ValueError(f"align_depth: captured {Dc.shape} and estimated {De.shape} depth must both be "
                         f"({K.height}, {K.width})")
    Dc[Dc < 0] = 0.0
    De[De < 0] = 0.0
    cfg = config
    scale = fit_scale_ransac(Dc, De, cfg) if cfg.fit_scale else 1.0
    De = De * scale
    Dc = np.ascontiguousarray(Dc)
    De = np.ascontiguousarray(De)
    Nc = depth_normals(Dc, K, cfg.normal_step_px, cfg.normal_max_jump_rel)
    Ne = depth_normals(De, K, cfg.normal_step_px, cfg.normal_max_jump_rel)
    if cfg.backend == "reference":
        O, C, sums = _ref_align(Dc, De, Nc, Ne, cfg)
    else:
        O, C, sums = _align_nb(Dc, De, Nc, Ne, float(cfg.agree_rel), float(np.cos(np.radians(cfg.max_normal_angle_deg))),
                               float(cfg.unmatched_cost), float(cfg.offset_penalty), int(cfg.max_offset_px),
                               int(cfg.max_passes), float(cfg.stop_rel))
    H, W = Dc.shape
    vv, uu = np.mgrid[0:H, 0:W]
    pv = np.clip(vv + O[..., 1], 0, H - 1)
    pu = np.clip(uu + O[..., 0], 0, W - 1)
    aligned = Dc[pv, pu].astype(np.float32)
    return AlignedDepth(aligned, O.astype(np.int32), C.astype(np.float32), float(scale),
                        tuple(float(s) for s in sums))
