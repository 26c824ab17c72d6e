"""Fast exact ADD-S for many poses of one model (CPU, numba).

ADD-S (bop ``adi``) queries, for every GT-posed model point, its nearest estimate-posed point.
Moving both into the estimate's model frame (``q = R_e^T (R_g x + t_g - t_e)``) makes the searched
set the *fixed* model, so one spatial index per object serves every pose.

The index is a regular grid over the model's box (plus a margin) whose cells hold candidate lists:
for a cell with centre g and half-diagonal h, any query q in the cell has d(q) <= d(g) + h, so its
nearest model point p satisfies |p - g| <= d(q) + h <= d(g) + 2h. Listing all points within that
radius of g makes the lookup exact. Queries outside the grid (grossly wrong poses) are answered by a
KD-tree afterwards, so results equal the reference to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["NNGridConfig", "NNGrid", "adi_batch_grid", "adi_batch_kdtree"]


@dataclass(frozen=True)
class NNGridConfig:
    """Grid index parameters."""

    max_cells: int = 48 ** 3
    """Upper bound on the number of grid cells (memory ~ cells x mean candidates x 4 bytes)."""
    margin_frac: float = 0.5
    """Grid margin around the model's bounding box, as a fraction of the box diagonal.
    Queries beyond it go to the KD-tree fallback."""


@nb.njit(parallel=True, cache=True)
def _count_candidates(centres, radius2, pts):  # pragma: no cover - numba
    n_c = centres.shape[0]
    counts = np.zeros(n_c, np.int64)
    for c in nb.prange(n_c):
        k = 0
        for j in range(pts.shape[0]):
            dx = pts[j, 0] - centres[c, 0]
            dy = pts[j, 1] - centres[c, 1]
            dz = pts[j, 2] - centres[c, 2]
            if dx * dx + dy * dy + dz * dz <= radius2[c]:
                k += 1
        counts[c] = k
    return counts


@nb.njit(parallel=True, cache=True)
def _fill_candidates(centres, radius2, pts, starts, cand, cand_r):  # pragma: no cover - numba
    for c in nb.prange(centres.shape[0]):
        k = starts[c]
        for j in range(pts.shape[0]):
            dx = pts[j, 0] - centres[c, 0]
            dy = pts[j, 1] - centres[c, 1]
            dz = pts[j, 2] - centres[c, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= radius2[c]:
                cand[k] = j
                cand_r[k] = np.sqrt(d2)
                k += 1
        # Sort the cell's candidates by distance to the centre: lookups stop early (see kernel).
        order = np.argsort(cand_r[starts[c]:k])
        cand[starts[c]:k] = cand[starts[c]:k][order]
        cand_r[starts[c]:k] = cand_r[starts[c]:k][order]


@nb.njit(parallel=True, cache=True)
def _adi_grid_kernel(A, G, Q, query_pts, lo, cell, dims, starts, cand, cand_r, model_pts):  # pragma: no cover - numba
    """For each pose e: sum of NN distances of points A[e] @ [x;1] inside the grid, and the
    number of points that fell outside it. The neighbour is searched in the model frame; its
    distance is then measured in the camera frame, |G[e] [x;1] - Q[e] [y;1]| (G: GT pose, Q:
    estimate), so slightly non-orthonormal rotations give bop's value exactly."""
    n_e = A.shape[0]
    n = query_pts.shape[0]
    sums = np.zeros(n_e)
    n_out = np.zeros(n_e, np.int64)
    for e in nb.prange(n_e):
        s = 0.0
        o = 0
        for i in range(n):
            x, y, z = query_pts[i, 0], query_pts[i, 1], query_pts[i, 2]
            qx = A[e, 0, 0] * x + A[e, 0, 1] * y + A[e, 0, 2] * z + A[e, 0, 3]
            qy = A[e, 1, 0] * x + A[e, 1, 1] * y + A[e, 1, 2] * z + A[e, 1, 3]
            qz = A[e, 2, 0] * x + A[e, 2, 1] * y + A[e, 2, 2] * z + A[e, 2, 3]
            fx = (qx - lo[0]) / cell
            fy = (qy - lo[1]) / cell
            fz = (qz - lo[2]) / cell
            if not (fx >= 0.0 and fy >= 0.0 and fz >= 0.0 and fx < dims[0] and fy < dims[1] and fz < dims[2]):
                o += 1
                continue
            ix, iy, iz = int(fx), int(fy), int(fz)
            c = (ix * dims[1] + iy) * dims[2] + iz
            gx = qx - (lo[0] + (ix + 0.5) * cell)
            gy = qy - (lo[1] + (iy + 0.5) * cell)
            gz = qz - (lo[2] + (iz + 0.5) * cell)
            dq = np.sqrt(gx * gx + gy * gy + gz * gz)
            best = np.inf
            jbest = -1
            for k in range(starts[c], starts[c + 1]):
                # |p - q| >= |p - g| - |q - g|: once that lower bound passes the best, stop
                # (candidates are sorted by |p - g|).
                lb = cand_r[k] - dq
                if lb > 0.0 and lb * lb > best:
                    break
                j = cand[k]
                dx = model_pts[j, 0] - qx
                dy = model_pts[j, 1] - qy
                dz = model_pts[j, 2] - qz
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best:
                    best = d2
                    jbest = j
            px = G[e, 0, 0] * x + G[e, 0, 1] * y + G[e, 0, 2] * z + G[e, 0, 3]
            py = G[e, 1, 0] * x + G[e, 1, 1] * y + G[e, 1, 2] * z + G[e, 1, 3]
            pz = G[e, 2, 0] * x + G[e, 2, 1] * y + G[e, 2, 2] * z + G[e, 2, 3]
            mx, my, mz = model_pts[jbest, 0], model_pts[jbest, 1], model_pts[jbest, 2]
            dx = px - (Q[e, 0, 0] * mx + Q[e, 0, 1] * my + Q[e, 0, 2] * mz + Q[e, 0, 3])
            dy = py - (Q[e, 1, 0] * mx + Q[e, 1, 1] * my + Q[e, 1, 2] * mz + Q[e, 1, 3])
            dz = pz - (Q[e, 2, 0] * mx + Q[e, 2, 1] * my + Q[e, 2, 2] * mz + Q[e, 2, 3])
            s += np.sqrt(dx * dx + dy * dy + dz * dz)
        sums[e] = s
        n_out[e] = o
    return sums, n_out


def _model_frame(R_est, t_est, R_gt, t_gt):
    """A (E,3,4) maps a model point x to R_e^-1 (R_g x + t_g - t_e): the GT-posed point in the
    estimate's model frame, where the searched set is the fixed model. G, Q (E,3,4): [R_g|t_g],
    [R_e|t_e]. The inverse (not the transpose) keeps identical poses exact even when a file's
    rotation is slightly non-orthonormal (LM-O's GT is up to 2e-3 off)."""
    Rinv = np.linalg.inv(R_est)
    A = np.empty((len(R_est), 3, 4))
    A[:, :, :3] = Rinv @ R_gt
    A[:, :, 3] = np.einsum("eij,ej->ei", Rinv, t_gt - t_est)
    G = np.concatenate([R_gt, t_gt[:, :, None]], axis=2)
    Q = np.concatenate([R_est, t_est[:, :, None]], axis=2)
    return A, G, Q


def _camera_dists(x, y, G, Q):
    """|G [x;1] - Q [y;1]| for matched rows of x, y (n,3)."""
    return np.linalg.norm(x @ G[:, :3].T + G[:, 3] - (y @ Q[:, :3].T + Q[:, 3]), axis=1)


class NNGrid:
    """Exact nearest-neighbour distance index over fixed model points (N, 3).

    Build once per object (about a second for 10k points), then :meth:`adi` scores many poses.
    """

    def __init__(self, pts: np.ndarray, config: NNGridConfig = NNGridConfig()):
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"NNGrid: points must be (N, 3) with N > 0, got {pts.shape}")
        self.pts = pts
        self.tree = cKDTree(pts)
        lo, hi = pts.min(0), pts.max(0)
        diag = float(np.linalg.norm(hi - lo)) or 1e-6
        margin = config.margin_frac * diag
        lo, hi = lo - margin, hi + margin
        ext = hi - lo
        cell = float(np.cbrt(np.prod(ext) / config.max_cells))
        dims = np.maximum(np.ceil(ext / cell).astype(np.int64), 1)
        self.lo, self.cell, self.dims = lo, cell, dims
        ii, jj, kk = np.meshgrid(*(np.arange(d) for d in dims), indexing="ij")
        centres = lo + (np.stack([ii, jj, kk], -1).reshape(-1, 3) + 0.5) * cell
        d_centre, _ = self.tree.query(centres, k=1)
        half_diag = 0.5 * np.sqrt(3.0) * cell
        # 1e-9 relative slack: the bound is exact, the slack only guards float rounding.
        radius2 = (d_centre + 2.0 * half_diag) ** 2 * (1 + 1e-9) + 1e-18
        counts = _count_candidates(centres, radius2, pts)
        self.starts = np.zeros(len(centres) + 1, np.int64)
        np.cumsum(counts, out=self.starts[1:])
        self.cand = np.empty(int(self.starts[-1]), np.int32)
        self.cand_r = np.empty(int(self.starts[-1]), np.float64)
        _fill_candidates(centres, radius2, pts, self.starts, self.cand, self.cand_r)

        # Query the model's own points in grid-cell order: consecutive lookups touch nearby cells.
        f = np.floor((pts - lo) / cell).astype(np.int64)
        self._query_order = np.ascontiguousarray(pts[np.argsort((f[:, 0] * dims[1] + f[:, 1]) * dims[2] + f[:, 2])])

    @property
    def mean_candidates(self) -> float:
        return float(self.starts[-1]) / max(len(self.starts) - 1, 1)

    def adi(self, R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
            query_pts: np.ndarray | None = None) -> np.ndarray:
        """ADD-S of E poses: R_* (E, 3, 3), t_* (E, 3) -> (E,) (units of the points).

        ``query_pts`` are the GT-posed points (default: the indexed points themselves, which is
        bop's ``adi`` with one point set).
        """
        R_est = np.asarray(R_est, dtype=np.float64).reshape(-1, 3, 3)
        R_gt = np.asarray(R_gt, dtype=np.float64).reshape(-1, 3, 3)
        t_est = np.asarray(t_est, dtype=np.float64).reshape(-1, 3)
        t_gt = np.asarray(t_gt, dtype=np.float64).reshape(-1, 3)
        E = len(R_est)
        if not (len(R_gt) == len(t_est) == len(t_gt) == E):
            raise ValueError("NNGrid.adi: R_est, t_est, R_gt, t_gt must have the same batch size")
        q = self._query_order if query_pts is None else np.ascontiguousarray(query_pts, dtype=np.float64)
        if E == 0:
            return np.zeros(0)
        A, G, Q = _model_frame(R_est, t_est, R_gt, t_gt)
        sums, n_out = _adi_grid_kernel(A, G, Q, q, self.lo, self.cell, self.dims, self.starts, self.cand,
                                       self.cand_r, self.pts)
        for e in np.nonzero(n_out)[0]:
            # Rare for plausible poses: points beyond the grid margin go to the KD-tree.
            qe = q @ A[e, :, :3].T + A[e, :, 3]
            f = (qe - self.lo) / self.cell
            outside = ~np.all((f >= 0) & (f < self.dims), axis=1)
            _, j = self.tree.query(qe[outside], k=1)
            sums[e] += _camera_dists(q[outside], self.pts[j], G[e], Q[e]).sum()
        return sums / len(q)


def adi_batch_grid(R_est, t_est, R_gt, t_gt, pts, config: NNGridConfig = NNGridConfig()) -> np.ndarray:
    """Convenience: build an :class:`NNGrid` over ``pts`` and score E poses (see NNGrid.adi)."""
    return NNGrid(pts, config).adi(R_est, t_est, R_gt, t_gt)


def adi_batch_kdtree(pts, R_est, t_est, R_gt, t_gt, tree: cKDTree | None = None) -> np.ndarray:
    """ADD-S of E poses with one KD-tree over the model and one batched query (E*N points).

    Same model-frame trick as :class:`NNGrid`; cheaper than the grid for a few hundred poses.
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    R_est = np.asarray(R_est, dtype=np.float64).reshape(-1, 3, 3)
    R_gt = np.asarray(R_gt, dtype=np.float64).reshape(-1, 3, 3)
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1, 3)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(-1, 3)
    tree = cKDTree(pts) if tree is None else tree
    out = np.empty(len(R_est))
    A, G, Q = _model_frame(R_est, t_est, R_gt, t_gt)
    step = max(1, 4_000_000 // len(pts))  # bound the query buffer to ~100 MB
    for s in range(0, len(R_est), step):
        sl = slice(s, s + step)
        q = np.matmul(pts, np.swapaxes(A[sl, :, :3], 1, 2)) + A[sl, None, :, 3]
        _, j = tree.query(q.reshape(-1, 3), k=1, workers=-1)
        j = j.reshape(-1, len(pts))
        # Distance of the found neighbour measured in the camera frame (see _model_frame).
        p_gt = np.matmul(pts, np.swapaxes(G[sl, :, :3], 1, 2)) + G[sl, None, :, 3]
        p_est = np.matmul(pts[j], np.swapaxes(Q[sl, :, :3], 1, 2)) + Q[sl, None, :, 3]
        d = p_gt - p_est
        out[sl] = np.sqrt(np.einsum("eni,eni->en", d, d)).mean(axis=1)
    return out
