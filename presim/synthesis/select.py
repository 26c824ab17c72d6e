"""View selection (thesis §3.4.2): distance -> angle vs FOV -> zero-overlap removal -> order.

1. Rank all input views by camera-centre distance to the target (eq. 3.5), keep the top
   ``max_candidates`` (the thesis' "local group" of ten).
2. Drop views whose viewing direction (optical axis) makes an angle (eq. 3.6) larger than the input
   camera's horizontal field of view with the target's.
3. Drop views with zero overlap: a sub-sampled grid of the view's valid depth pixels (every
   ``overlap_stride_px``-th pixel, prepared once per view) is projected into the target; the overlap
   is the fraction of those points that land inside the target image in front of the camera.
4. Fallback: when steps 1-3 leave no view (the target looks where none of the nearest views
   looked), the ``max_candidates`` views of smallest viewing angle (any distance) that overlap the
   target are used, largest overlap first, so a robot's camera still gets an image wherever some
   view saw the scene.
5. Order the survivors: by distance (default) or by overlap, descending. Which view is warped
   first matters most — it is the only view that covers the whole image, later ones only fill
   holes — and the nearest view proved better than the largest overlap on the real capture
   (leave-one-out PSNR, docs/synthesis.md).

Ablations (thesis Table 3.4): ``mode="distance"`` keeps the ``max_candidates`` nearest views in
distance order; ``mode="angle"`` the ``max_candidates`` views of smallest angle in angle order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from presim.geometry import Intrinsics, invert, project, transform_points

__all__ = ["SELECTION_MODES", "VIEW_ORDERS", "Selection", "view_overlap", "select_views"]

SELECTION_MODES = ("adaptive", "distance", "angle")
VIEW_ORDERS = ("overlap", "distance")


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


def view_overlap(grid_xyz_world: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics,
                 near_m: float = 1e-3) -> float:
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
    """(k,) overlaps of ``idx`` in order until ``n_exact`` of them are > 0; the views after those get
    ``overlapping``'s test only: nan where they overlap, 0 where they do not."""
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


def select_views(T_world_cam: np.ndarray, K: Intrinsics, centres_world: np.ndarray,
                 directions_world: np.ndarray, hfov_deg: np.ndarray,
                 grid_points: Callable[[int], np.ndarray], mode: str = "adaptive",
                 max_candidates: int = 10, order: str = "distance",
                 overlaps: Callable[[np.ndarray], np.ndarray] | None = None,
                 overlapping: Callable[[np.ndarray], np.ndarray] | None = None,
                 exact_overlaps: int = 0) -> Selection:
    """Select and order the input views for a target camera.

    Args:
        T_world_cam: 4x4 target pose; K: target intrinsics.
        centres_world: (N, 3) input camera centres; directions_world: (N, 3) unit optical axes.
        hfov_deg: (N,) horizontal field of view of each input camera.
        grid_points: ``grid_points(i)`` -> (m, 3) float32 world points of view i's sub-sampled grid
            (only called for views that reach the overlap test).
        mode: ``"adaptive"`` (thesis), ``"distance"`` or ``"angle"``.
        max_candidates: size of the local group.
        order: ``"distance"`` or ``"overlap"`` (thesis mode only).
        overlaps: optional fast path: ``overlaps(idx)`` -> (k,) :func:`view_overlap` of each view of
            ``idx`` in the target (the Renderer projects all grids in one call,
            :class:`presim.synthesis.grids.FrameGrids`); None = :func:`view_overlap` per view.
        overlapping: optional fast path with ``exact_overlaps`` > 0 and ``order="distance"``:
            ``overlapping(idx)`` -> bool (k,) = ``overlaps(idx) > 0`` (cheaper: it may stop at the
            first grid point that lands in the target). Only the first ``exact_overlaps`` selected
            views then get their overlap computed (the Renderer passes ``max_views``: the adaptive
            loop never draws beyond them); later selected views report nan. The selected views and
            their order are the same.
    """
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
