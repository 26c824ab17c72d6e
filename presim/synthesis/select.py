"""View selection (thesis §3.4.2): distance -> angle vs FOV -> zero-overlap removal -> order.

Ablations (thesis Table 3.4): ``mode="distance"`` (nearest first), ``mode="angle"`` (smallest angle first)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from presim.geometry import Intrinsics, invert, project, transform_points
from presim.synthesis.config import SELECTION_MODES, VIEW_ORDERS

__all__ = ["Selection", "view_overlap", "select_views", "ring_views"]


@dataclass(frozen=True)
class Selection:
    """Selected views for one target pose, in warping order."""

    view_idx: np.ndarray
    """int64 (k,) scene frame positions, in the order they are warped."""
    distance_m: np.ndarray
    """(k,) camera-centre distances to the target."""
    angle_deg: np.ndarray
    """(k,) angles between viewing directions."""
    overlap_frac: np.ndarray
    """(k,) overlap of the view's sub-sampled grid with the target image (nan when not computed)."""


def view_overlap(grid_xyz_world: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics, near_m: float = 1e-3) -> float:
    """Fraction of the world points (m, 3) that project inside the target image, in front of it."""
    if len(grid_xyz_world) == 0:
        return 0.0
    uv, z = project(K, transform_points(T_cam_world, grid_xyz_world))
    with np.errstate(invalid="ignore"):
        inside = (z > near_m) & (uv[:, 0] >= -0.5) & (uv[:, 0] < K.width - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] < K.height - 0.5)
    return float(inside.mean())


def _first_overlaps(idx: np.ndarray, overlaps: Callable[[np.ndarray], np.ndarray],
                    overlapping: Callable[[np.ndarray], np.ndarray], n_exact: int) -> np.ndarray:
    """(k,) overlaps of ``idx`` until ``n_exact`` are > 0; later views get ``overlapping`` only (nan / 0)."""
    ov = np.full(len(idx), np.nan)
    done = found = 0
    while done < len(idx) and found < n_exact:
        part = np.asarray(overlaps(idx[done:done + n_exact - found]), np.float64).reshape(-1)
        ov[done:done + len(part)] = part
        found += int(np.count_nonzero(part > 0.0))
        done += len(part)
    if done < len(idx):
        ov[done:][~np.asarray(overlapping(idx[done:]), bool)] = 0.0
    return ov


def select_views(T_world_cam: np.ndarray, K: Intrinsics, centres_world: np.ndarray, directions_world: np.ndarray,
                 hfov_deg: np.ndarray, grid_points: Callable[[int], np.ndarray], mode: str = "adaptive",
                 max_candidates: int = 10, order: str = "distance",
                 overlaps: Callable[[np.ndarray], np.ndarray] | None = None,
                 overlapping: Callable[[np.ndarray], np.ndarray] | None = None, exact_overlaps: int = 0) -> Selection:
    """Select and order the input views for a target camera (4x4 ``T_world_cam``). centres_world, directions_world:
    (N, 3) input camera centres and unit optical axes; hfov_deg: (N,); grid_points(i) -> (m, 3) world points of view
    i's grid; order: adaptive mode only. ``overlaps(idx)`` -> (k,) :func:`view_overlap` per view (fast path:
    :class:`presim.synthesis.grids.FrameGrids`); with ``overlapping(idx)`` -> ``overlaps(idx) > 0`` and
    ``exact_overlaps`` > 0 (distance order) only the first ``exact_overlaps`` views get an overlap, later ones nan
    (same selection)."""
    if mode not in SELECTION_MODES:
        raise ValueError(f"selection must be one of {SELECTION_MODES}, got {mode!r}")
    if order not in VIEW_ORDERS:
        raise ValueError(f"view order must be one of {VIEW_ORDERS}, got {order!r}")
    if max_candidates < 1:
        raise ValueError(f"max_candidates must be >= 1, got {max_candidates}")
    T_world_cam = np.asarray(T_world_cam, np.float64)
    dist = np.linalg.norm(centres_world - T_world_cam[:3, 3], axis=1)
    cosang = np.clip(directions_world @ T_world_cam[:3, 2], -1.0, 1.0)
    angle = np.degrees(np.arccos(cosang))
    n = len(dist)
    k = min(max_candidates, n)
    if mode == "angle":
        idx = np.lexsort((dist, angle))[:k]
        return Selection(idx, dist[idx], angle[idx], np.full(len(idx), np.nan))
    idx = np.lexsort((angle, dist))[:k]  # by distance, ties by angle
    if mode == "distance":
        return Selection(idx, dist[idx], angle[idx], np.full(len(idx), np.nan))
    idx = idx[angle[idx] <= hfov_deg[idx]]
    T_cam_world = invert(T_world_cam)
    if overlaps is None:
        def overlaps(ids: np.ndarray) -> np.ndarray:
            return np.array([view_overlap(grid_points(int(i)), T_cam_world, K) for i in ids], np.float64)
    if overlapping is not None and exact_overlaps > 0 and order == "distance":
        ov = _first_overlaps(idx, overlaps, overlapping, exact_overlaps)
        keep = ~(ov <= 0.0)  # nan: overlaps, fraction not computed
    else:
        ov = np.asarray(overlaps(idx), np.float64).reshape(len(idx))
        keep = ov > 0.0
    idx, ov = idx[keep], ov[keep]
    if len(idx) == 0:  # fallback (step 4): the views looking most like the target, any distance
        idx = np.lexsort((dist, angle))[:k]
        ov = np.asarray(overlaps(idx), np.float64).reshape(len(idx))
        o = np.argsort(-ov, kind="stable")
        idx, ov = idx[o], ov[o]
        keep = ov > 0.0
        return Selection(idx[keep], dist[idx[keep]], angle[idx[keep]], ov[keep])
    if order == "overlap":
        # Stable sort on rounded overlap so near-equal overlaps keep the distance order.
        o = np.argsort(-np.round(ov, 2), kind="stable")
        idx, ov = idx[o], ov[o]
    return Selection(idx, dist[idx], angle[idx], ov)


def ring_views(T_world_cam: np.ndarray, centres_world: np.ndarray, directions_world: np.ndarray,
               hfov_deg: np.ndarray, skip: int, n: int, overlapping: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The ring beyond the local group: int64 positions of the views ranked ``skip`` to ``skip + n`` by centre
    distance (ties by angle, as :func:`select_views`) whose angle to the target is within their FOV and for which
    ``overlapping(idx)`` -> bool (k,) holds, nearest first."""
    T_world_cam = np.asarray(T_world_cam, np.float64)
    dist = np.linalg.norm(centres_world - T_world_cam[:3, 3], axis=1)
    angle = np.degrees(np.arccos(np.clip(directions_world @ T_world_cam[:3, 2], -1.0, 1.0)))
    ring = np.lexsort((angle, dist))[skip:skip + max(n, 0)]
    ring = ring[angle[ring] <= hfov_deg[ring]]
    if len(ring):
        ring = ring[np.asarray(overlapping(ring), bool).reshape(len(ring))]
    return ring.astype(np.int64)
