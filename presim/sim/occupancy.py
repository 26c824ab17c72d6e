"""Floor and collisions: a 2D occupancy map from the scene's point cloud, and base motion against it.

Obstacles are the scene points whose height above the floor lies between ``floor_margin_m`` (lower
points are floor, or bumps a base rolls over) and the robot's height. They are binned into square
cells of ``resolution_m`` (default 5 cm) in the floor plane; a cell with at least
``min_points_per_cell`` such points is occupied. A cell is *known* (inside the captured area) when any
scene point falls in its column. The base is a disc of the footprint radius, so its centre is blocked
where the distance to the nearest occupied cell centre is below ``radius + resolution/2`` (the map
inflated by the footprint radius plus half a cell, so a cell is treated as its full square).

Motion (:func:`move_base`) is checked in sub-steps of at most half a cell, so a thin wall can never be
jumped; a blocked sub-step slides along the obstacle (the component of the motion tangent to the
distance field's level line) or, when that is blocked too, stops. Either way the step reports contact.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from presim.capture.scene import FloorPlane

__all__ = ["OccupancyConfig", "OccupancyMap", "build_occupancy_map", "move_base", "plan_path"]


@dataclass(frozen=True)
class OccupancyConfig:
    """How the occupancy map is built from the scene's points."""

    resolution_m: float = 0.05
    """Cell size, metres."""
    floor_margin_m: float = 0.10
    """Points lower than this above the floor are floor (depth noise, rugs, thresholds)."""
    min_points_per_cell: int = 2
    """Obstacle points needed to mark a cell occupied (rejects isolated depth outliers)."""
    padding_m: float = 1.0
    """Map margin around the scene points (unknown cells: driving there is allowed but reported)."""
    known_dilate_m: float = 0.15
    """Columns within this distance of a column holding scene points count as known too (closes the
    gaps between the points of a sparse cloud)."""
    view_known_radius_m: float = 1.0
    """Cells this close to where a captured camera stood count as known (the camera rarely sees the
    floor under itself)."""


@dataclass(frozen=True)
class OccupancyMap:
    """Occupancy grid in the floor plane (world x, y). Cell (row i, col j) covers
    ``x in [ox + j*res, ox + (j+1)*res)``, ``y in [oy + i*res, oy + (i+1)*res)``."""

    origin_xy: np.ndarray
    """(2,) world (x, y) of the grid's corner, metres."""
    resolution_m: float
    occupied: np.ndarray
    """bool (H, W)."""
    known: np.ndarray
    """bool (H, W): the capture saw this column (some scene point lies in it)."""
    dist_m: np.ndarray
    """float32 (H, W): distance from each cell centre to the nearest occupied cell centre."""
    radius_m: float
    """Footprint radius the map is checked against."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        return (int(np.floor((y - self.origin_xy[1]) / self.resolution_m)),
                int(np.floor((x - self.origin_xy[0]) / self.resolution_m)))

    def cell_centre(self, i: int, j: int) -> tuple[float, float]:
        return (float(self.origin_xy[0] + (j + 0.5) * self.resolution_m),
                float(self.origin_xy[1] + (i + 0.5) * self.resolution_m))

    def _inside(self, i: int, j: int) -> bool:
        return 0 <= i < self.shape[0] and 0 <= j < self.shape[1]

    def distance(self, x: float, y: float) -> float:
        """Distance (m) from the cell containing (x, y) to the nearest obstacle; inf outside the map."""
        i, j = self.cell_of(x, y)
        return float(self.dist_m[i, j]) if self._inside(i, j) else np.inf

    @property
    def blocked_below_m(self) -> float:
        return self.radius_m + 0.5 * self.resolution_m

    def is_blocked(self, x: float, y: float) -> bool:
        return self.distance(x, y) < self.blocked_below_m

    def is_known(self, x: float, y: float) -> bool:
        i, j = self.cell_of(x, y)
        return bool(self.known[i, j]) if self._inside(i, j) else False

    def free_mask(self, clearance_m: float = 0.0, include_unknown: bool = False) -> np.ndarray:
        """bool (H, W): cells where the base centre fits with ``clearance_m`` to spare; only known
        cells unless ``include_unknown``."""
        fits = self.dist_m >= self.blocked_below_m + clearance_m
        return fits if include_unknown else fits & self.known


def build_occupancy_map(points_xyz: np.ndarray, floor: FloorPlane, robot_height_m: float,
                        radius_m: float, config: OccupancyConfig = OccupancyConfig(),
                        view_xy: np.ndarray | None = None) -> OccupancyMap:
    """Occupancy map of ``points_xyz`` (float (M, 3) world metres) for a base of ``radius_m`` and
    height ``robot_height_m`` standing on ``floor`` (normal ~ +z; the world floor is z = 0 after import).

    Known cells: columns holding scene points (dilated by ``known_dilate_m``), cells within ``view_known_radius_m`` of ``view_xy``
    ((N, 2) floor positions of the captured cameras) and every cell enclosed by those (hole filling:
    the inside of a room whose walls were captured is known)."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"occupancy map needs a non-empty (M, 3) point cloud, got {pts.shape}")
    if abs(floor.normal[2]) < 0.9:
        raise ValueError(f"floor normal {floor.normal} is not close to +z; the scene's world frame must have gravity along -z")
    res = float(config.resolution_m)
    h = floor.height_of(pts)
    lo = pts[:, :2].min(axis=0) - config.padding_m
    hi = pts[:, :2].max(axis=0) + config.padding_m
    W, H = (np.ceil((hi - lo) / res).astype(int) + 1)
    j = np.floor((pts[:, 0] - lo[0]) / res).astype(np.int64)
    i = np.floor((pts[:, 1] - lo[1]) / res).astype(np.int64)
    lin = i * W + j
    known = np.bincount(lin, minlength=H * W).reshape(H, W) > 0
    if config.known_dilate_m > 0:
        known = ndimage.distance_transform_edt(~known) * res <= config.known_dilate_m
    if view_xy is not None and len(view_xy):
        vj = np.floor((np.asarray(view_xy)[:, 0] - lo[0]) / res).astype(np.int64)
        vi = np.floor((np.asarray(view_xy)[:, 1] - lo[1]) / res).astype(np.int64)
        ok = (vi >= 0) & (vi < H) & (vj >= 0) & (vj < W)
        seeds = np.zeros((H, W), bool)
        seeds[vi[ok], vj[ok]] = True
        near = ndimage.distance_transform_edt(~seeds) * res <= config.view_known_radius_m
        known |= near
    known = ndimage.binary_fill_holes(known)
    band = (h >= config.floor_margin_m) & (h <= robot_height_m)
    counts = np.bincount(lin[band], minlength=H * W).reshape(H, W)
    occupied = counts >= config.min_points_per_cell
    if occupied.any():
        dist = ndimage.distance_transform_edt(~occupied).astype(np.float32) * res
    else:
        dist = np.full((H, W), np.inf, np.float32)
    return OccupancyMap(lo, res, occupied, known, dist, float(radius_m))


def _gradient(occ: OccupancyMap, x: float, y: float) -> np.ndarray:
    """Unit direction of increasing obstacle distance at (x, y) (central differences), or zeros."""
    i, j = occ.cell_of(x, y)
    H, W = occ.shape
    i0, i1, j0, j1 = max(i - 1, 0), min(i + 1, H - 1), max(j - 1, 0), min(j + 1, W - 1)
    if not (0 <= i < H and 0 <= j < W):
        return np.zeros(2)
    d = np.minimum(occ.dist_m, 1e3)  # inf-safe
    g = np.array([d[i, j1] - d[i, j0], d[i1, j] - d[i0, j]], dtype=np.float64)
    n = np.linalg.norm(g)
    return g / n if n > 1e-9 else np.zeros(2)


def move_base(occ: OccupancyMap, x: float, y: float, x1: float, y1: float) -> tuple[float, float, bool]:
    """Move the base centre from (x, y) towards (x1, y1) against the map.

    Returns (x, y, contact). Sub-steps are at most half a cell long. A sub-step into a blocked cell is
    replaced by its slide along the obstacle; if that is blocked too the base stops there. A base that
    starts inside an inflated obstacle may move only where the obstacle distance does not shrink.
    """
    d = np.array([x1 - x, y1 - y], dtype=np.float64)
    length = float(np.hypot(*d))
    if length < 1e-12:
        return x, y, False
    n = max(1, int(np.ceil(length / (0.5 * occ.resolution_m))))
    step = d / n
    p = np.array([x, y], dtype=np.float64)
    contact = False

    def ok(q: np.ndarray, cur: np.ndarray) -> bool:
        dq = occ.distance(*q)
        return dq >= occ.blocked_below_m or dq > occ.distance(*cur)

    for _ in range(n):
        q = p + step
        if ok(q, p):
            p = q
            continue
        contact = True
        g = _gradient(occ, *p)
        slid = False
        candidates = []
        if np.any(g):
            t = np.array([-g[1], g[0]])
            candidates.append(t * (step @ t))
        candidates += [np.array([step[0], 0.0]), np.array([0.0, step[1]])]
        for s in candidates:
            if np.hypot(*s) > 1e-9 and ok(p + s, p):
                p = p + s
                slid = True
                break
        if not slid:
            break
    return float(p[0]), float(p[1]), contact


def plan_path(occ: OccupancyMap, start_xy: tuple[float, float], goal_xy: tuple[float, float],
              clearance_m: float = 0.05, unknown_cost: float = 4.0) -> np.ndarray | None:
    """Shortest 8-connected path on the cells the base fits in (Dijkstra), simplified by line of
    sight. Unknown cells may be crossed at ``unknown_cost`` times the length (the capture may not
    have seen the floor there). Returns (K, 2) world waypoints ending at the goal's cell centre, or
    None if unreachable."""
    free = occ.free_mask(clearance_m, include_unknown=True)
    weight = np.where(occ.known, 1.0, float(unknown_cost))
    H, W = free.shape
    s, g = occ.cell_of(*start_xy), occ.cell_of(*goal_xy)
    if not (0 <= g[0] < H and 0 <= g[1] < W and free[g]):
        return None
    if not (0 <= s[0] < H and 0 <= s[1] < W):
        return None
    cost = np.full((H, W), np.inf)
    prev = -np.ones((H, W), np.int64)
    cost[s] = 0.0
    heap = [(0.0, s[0], s[1])]
    moves = [(di, dj, float(np.hypot(di, dj))) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    while heap:
        c, i, j = heapq.heappop(heap)
        if (i, j) == g:
            break
        if c > cost[i, j]:
            continue
        for di, dj, w in moves:
            a, b = i + di, j + dj
            if 0 <= a < H and 0 <= b < W and free[a, b]:
                cw = c + w * weight[a, b]
                if cw < cost[a, b]:
                    cost[a, b] = cw
                    prev[a, b] = i * W + j
                    heapq.heappush(heap, (cw, a, b))
    if not np.isfinite(cost[g]):
        return None
    cells = [g]
    while cells[-1] != s:
        k = prev[cells[-1]]
        cells.append((int(k // W), int(k % W)))
    cells.reverse()
    pts = np.array([occ.cell_centre(i, j) for i, j in cells])

    def visible(a: np.ndarray, b: np.ndarray) -> bool:
        m = max(2, int(np.ceil(np.hypot(*(b - a)) / (0.5 * occ.resolution_m))))
        for t in np.linspace(0.0, 1.0, m):
            i, j = occ.cell_of(*(a + t * (b - a)))
            if not (0 <= i < H and 0 <= j < W and free[i, j]):
                return False
        return True

    out = [pts[0]]
    k = 0
    while k < len(pts) - 1:
        nxt = k + 1
        for m in range(len(pts) - 1, k, -1):
            if visible(pts[k], pts[m]):
                nxt = m
                break
        out.append(pts[nxt])
        k = nxt
    return np.array(out[1:]) if len(out) > 1 else pts[-1:]
