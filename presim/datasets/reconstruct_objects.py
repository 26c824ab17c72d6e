"""Objects of a capture reconstructed in its world frame from multi-view depth (thesis §5.3.5).

Two steps, each one pure function with its config:

1. :func:`find_object_boxes` -- where the objects are. The scene's depth is fused into a 1 cm cloud;
   horizontal support planes (floor, table top, shelf/bin bottom) are found by sequential RANSAC
   (seeded, so every run finds the same planes) and planes split from one surface are merged; the
   *working plane* is the one the frames aim at, each aim weighed 1/z^2 (close views count most);
   the points standing on its footprint are clustered (Open3D DBSCAN) and every cluster of object
   size that touches the plane becomes an oriented box (z = the plane's up normal, x/y = principal
   axes of the footprint). Or the user gives the boxes (:func:`read_boxes_json`).
2. :func:`reconstruct_objects` -- per box, the thesis' Algorithm 3: every pixel of every frame
   (``stride``) whose depth falls in the box is a candidate; candidates are merged per
   ``voxel_m`` voxel (mean position and colour: "no similar point is added twice"); a merged point
   is kept when more than ``min_views`` frames see it (it projects into the image and the frame's
   depth agrees within ``view_tol_m``); the statistical outlier filter (PCL's
   StatisticalOutlierRemoval, here Open3D's) removes the rest; normals are estimated and turned
   towards the cameras that saw each point. A watertight Poisson mesh is made when the cloud
   is closed by its support plane (a bottom cap of the footprint is added: the object stands on
   it) and the mesh stays within ``mesh_max_dev_m`` of the cloud; otherwise the cloud is the
   model.

:func:`write_objects_into_scene` stores the result in the scene folder atomically: the models go to a
new ``objects/recon-<run>/`` folder (renamed into place complete), then ``scene.json`` is rewritten
in one atomic replace (objects it held before are kept under ``objects_replaced``).

Example:
    >>> from presim.capture.store import load_scene
    >>> scene = load_scene("out/sample")                                   # doctest: +SKIP
    >>> boxes, planes = find_object_boxes(scene)                           # doctest: +SKIP
    >>> objs = reconstruct_objects(scene, boxes, support=planes)           # doctest: +SKIP
    >>> write_objects_into_scene("out/sample", objs)                       # doctest: +SKIP
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from presim.capture.scene import Scene, SceneError
from presim.datasets.object_sources import read_json_items
from presim.formats.ply import write_ply
from presim.geometry import invert, make_pose, transform_points, unproject_depth
from presim.io_utils import atomic_write_json, progress

__all__ = ["ObjectReconConfig", "SupportPlane", "ObjectBox", "ReconstructedObject", "ObjectReconError",
           "find_object_boxes", "read_boxes_json", "check_boxes_disjoint", "reconstruct_objects",
           "write_objects_into_scene", "boxes_overlap"]


class ObjectReconError(SceneError):
    """The objects of a capture cannot be found or reconstructed; the message says what failed."""


@dataclass(frozen=True)
class ObjectReconConfig:
    """Parameters of object finding and reconstruction (metres)."""

    refined: bool = True
    """Use ``depth_refined.npy`` (``presim refine``) when the scene has it (thesis: the refined depth
    of §5.3.4); else the raw depth."""
    frame_step: int = 1
    """Use every n-th frame."""
    seg_voxel_m: float = 0.01
    """Voxel of the fused cloud used to find planes and clusters."""
    seg_stride: int = 4
    """Pixel stride of the fused segmentation cloud."""
    plane_dist_m: float = 0.012
    """RANSAC inlier distance of a support plane (raw consumer depth is noisy by ~1 cm at 1.5 m)."""
    max_tilt_deg: float = 20.0
    """A support plane's normal is within this angle of up (against gravity)."""
    max_planes: int = 8
    """Planes extracted one after another (their inliers removed)."""
    ransac_iterations: int = 500
    """Random point triples tried per plane."""
    min_plane_frac: float = 0.01
    """A support plane holds at least this fraction of the fused cloud's upward-facing points."""
    min_plane_area_m2: float = 0.01
    """... and covers at least this area (in ``seg_voxel_m`` voxels): smaller flat patches (a box
    top, a book, a few noisy voxels that a tilted triple happens to fit) are not supports."""
    merge_dist_m: float = 0.02
    """Planes whose inliers lie (median) within this of a larger plane are one surface (a noisy or
    voxel-quantised table top splits into layers 1 cm apart) and are merged."""
    min_height_m: float = 0.012
    """Points lower than this above their plane belong to the plane."""
    max_object_size_m: float = 0.45
    """Clusters larger than this along any box axis are furniture or walls, not objects."""
    min_object_size_m: float = 0.03
    """Clusters whose largest side is smaller are noise."""
    cluster_eps_m: float = 0.02
    """DBSCAN neighbourhood radius (2 fused voxels: neighbouring objects closer than this merge)."""
    cluster_min_points: int = 6
    """DBSCAN core-point neighbours (a 2 cm disc of a 1 cm-voxel surface holds ~12 points)."""
    min_cluster_points: int = 30
    """Clusters with fewer fused voxels are noise."""
    touch_m: float = 0.03
    """A cluster's lowest point is at most this far above its plane (the object stands on it)."""
    box_margin_m: float = 0.01
    """Margin added to a found box on every side (not below the plane)."""
    stride: int = 2
    """Pixel stride of the reconstruction candidates."""
    voxel_m: float = 0.002
    """Candidates closer than this (one voxel) are merged into one point (mean position, colour)."""
    min_views: int = 5
    """A point is kept when MORE than this many frames see it (thesis: visible in more than five)."""
    view_tol_m: float = 0.01
    """A frame sees a point when its depth at the point's pixel is within this of the point's depth."""
    sor_neighbors: int = 20
    """Statistical outlier removal: neighbours per point."""
    sor_std_ratio: float = 2.0
    """Statistical outlier removal: points whose mean neighbour distance is beyond mean + ratio * std
    are removed."""
    normal_radius_m: float = 0.01
    """Radius of the normal estimation (hybrid with 30 neighbours)."""
    poisson_depth: int = 8
    """Octree depth of the Poisson reconstruction (2^8 cells over the object: ~1 mm for 25 cm)."""
    poisson_trim_quantile: float = 0.02
    """Poisson vertices with a sample density below this quantile are removed."""
    mesh_max_dev_m: float = 0.015
    """The mesh is kept when 99 % of its vertices are within this of the cloud (else the cloud is
    the model: Poisson invented surface where the data has a hole)."""
    all_planes: bool = False
    """Objects on every support plane; default: only on the *working* plane, the one the cameras
    aim at most (image-centre depth lands on or just above it) -- the table top, the bin bottom."""
    min_object_points: int = 200
    """An object with fewer kept points is not reconstructed."""


@dataclass(frozen=True)
class SupportPlane:
    """A horizontal plane ``normal . p + offset = 0`` (normal up) that objects stand on."""

    normal: np.ndarray
    offset: float
    num_points: int

    def height_of(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p) @ self.normal + self.offset


@dataclass(frozen=True)
class ObjectBox:
    """An oriented box holding one object, world frame: ``p_box = T_world_box^-1 p`` inside
    ``|p_box| <= size/2``."""

    name: str
    T_world_box: np.ndarray
    """4x4 box-to-world (box centre, axes)."""
    size_m: np.ndarray
    """(3,) side lengths along the box axes."""
    obj_id: int | None = None
    symmetric: bool = False
    support_idx: int | None = None
    """Index of the support plane the object stands on (a bottom cap closes the mesh), or None."""

    def contains(self, p_world: np.ndarray) -> np.ndarray:
        q = transform_points(invert(self.T_world_box), np.asarray(p_world, dtype=np.float64))
        return np.all(np.abs(q) <= 0.5 * np.asarray(self.size_m), axis=1)

    def corners(self) -> np.ndarray:
        s = 0.5 * np.asarray(self.size_m)
        c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * s
        return transform_points(self.T_world_box, c)


@dataclass
class ReconstructedObject:
    """One reconstructed object: a cloud (and maybe a mesh) in its object frame plus its world pose."""

    obj_id: int
    name: str
    T_world_obj: np.ndarray
    points_m: np.ndarray
    """float32 (P, 3) object frame."""
    colors: np.ndarray
    """uint8 (P, 3)."""
    normals: np.ndarray
    """float32 (P, 3) unit, pointing out (towards the cameras that saw them)."""
    views: np.ndarray
    """int32 (P,) number of frames that see each point."""
    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    mesh_colors: np.ndarray | None = None
    watertight: bool = False
    symmetric: bool = False
    frames_seen: int = 0
    """Frames whose depth has candidate pixels in the object's box."""
    stats: dict = field(default_factory=dict)


# ---- 1. finding the objects ----------------------------------------------------------------------

def _frame_indices(scene: Scene, config: ObjectReconConfig) -> list[int]:
    return list(range(0, len(scene), max(1, int(config.frame_step))))


def _depth(scene: Scene, i: int, config: ObjectReconConfig) -> np.ndarray:
    return np.asarray(scene.depth(i, refined=config.refined), dtype=np.float32)


def _fused_cloud(scene: Scene, config: ObjectReconConfig) -> np.ndarray:
    import open3d as o3d

    pts = []
    for i in _frame_indices(scene, config):
        p, _ = unproject_depth(scene.intrinsics[i], _depth(scene, i, config), scene.T_world_cam[i],
                               stride=config.seg_stride)
        if len(p):
            q = np.unique(np.floor(p / config.seg_voxel_m).astype(np.int64), axis=0)
            pts.append(q)
    if not pts:
        raise ObjectReconError(f"{scene.path}: no valid depth in any frame")
    q = np.unique(np.concatenate(pts), axis=0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((q + 0.5) * config.seg_voxel_m))
    return np.asarray(pc.points)


def _footprint(xy: np.ndarray, cell: float, close_px: int = 3):
    """Filled 2D occupancy grid of plane inliers (holes where objects hide the plane are closed)."""
    import cv2

    lo = xy.min(0) - cell * (close_px + 1)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    shape = tuple(ij.max(0) + close_px + 2)
    grid = np.zeros(shape, np.uint8)
    grid[ij[:, 0], ij[:, 1]] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * close_px + 1, 2 * close_px + 1))
    grid = cv2.morphologyEx(grid, cv2.MORPH_CLOSE, k)
    # Fill enclosed holes (an object's shadow on a table is enclosed by table points).
    ff = grid.copy()
    mask = np.zeros((shape[0] + 2, shape[1] + 2), np.uint8)
    cv2.floodFill(ff, mask, (0, 0), 1)
    grid = grid | (1 - ff)
    return lo, grid


def _plane_basis(n: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])  # (2, 3)


def find_object_boxes(scene: Scene, config: ObjectReconConfig = ObjectReconConfig()
                      ) -> tuple[list[ObjectBox], list[SupportPlane]]:
    """Find the objects standing on horizontal planes (see the module docstring).

    Returns ``(boxes, planes)``; boxes are named ``object_01``, ... in order of their distance to the
    cameras' mean viewing target. Raises :class:`ObjectReconError` naming what failed (no plane,
    no object).
    """
    import open3d as o3d

    pts = _fused_cloud(scene, config)
    up = -np.asarray(scene.gravity_world, dtype=np.float64)
    up /= np.linalg.norm(up)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    # Only points whose surface faces up can be on a support plane (walls, the ceiling and object
    # sides are left out of the RANSAC, so small table tops are not crowded out by walls).
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * config.seg_voxel_m, max_nn=30))
    cos_up = np.abs(np.asarray(pc.normals) @ up)
    remaining = np.flatnonzero(cos_up >= np.cos(np.radians(config.max_tilt_deg)))
    n_horizontal = len(remaining)
    planes: list[SupportPlane] = []
    plane_masks = []
    rng = np.random.default_rng(0)
    for _ in range(config.max_planes):
        if len(remaining) < max(100, config.min_plane_frac * n_horizontal):
            break
        n, d, inl = _ransac_plane(pts[remaining], config.plane_dist_m, config.ransac_iterations, rng)
        if len(inl) < max(config.min_plane_frac * n_horizontal, config.min_plane_area_m2 / config.seg_voxel_m ** 2):
            break
        if n @ up < 0:
            n, d = -n, -d
        idx = remaining[inl]
        remaining = np.setdiff1d(remaining, idx, assume_unique=True)
        if np.degrees(np.arccos(np.clip(n @ up, -1, 1))) <= config.max_tilt_deg:
            planes.append(SupportPlane(n, d, len(idx)))
            plane_masks.append(idx)
    if not planes:
        raise ObjectReconError(f"{scene.path}: no horizontal support plane found (floor, table top, shelf "
                               f"within {config.max_tilt_deg:.0f} deg of up holding >= "
                               f"{100 * config.min_plane_frac:.0f}% of the points); pass --boxes FILE")

    planes, plane_masks = _merge_split_planes(planes, plane_masks, pts, up, config)
    work = None if config.all_planes else _working_plane(scene, planes, plane_masks, pts, config)
    if work is not None:
        # The working plane refit on its own footprint region: a RANSAC plane that also spans
        # other furniture at about the same height is tilted by it (1 deg = 1.7 cm over a metre).
        k, (B, lo, grid), _ = work
        m = plane_masks[k]
        ij = np.floor((pts[m] @ B.T - lo) / (2 * config.seg_voxel_m)).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < np.array(grid.shape)), axis=1)
        on = np.zeros(len(m), bool)
        on[inside] = grid[ij[inside, 0], ij[inside, 1]] > 0
        if np.count_nonzero(on) >= 3:
            planes[k] = _fit_plane(pts[m[on]], up, pl_points=planes[k].num_points)
    # Each non-plane point belongs to the highest plane below it whose footprint it stands over.
    in_plane = np.zeros(len(pts), bool)
    for m in plane_masks:
        in_plane[m] = True
    cand = np.flatnonzero(~in_plane)
    owner = np.full(len(cand), -1)
    best_h = np.full(len(cand), np.inf)
    cell = 2 * config.seg_voxel_m
    for k, (pl, m) in enumerate(zip(planes, plane_masks)):
        B = _plane_basis(pl.normal)
        lo, grid = _footprint(pts[m] @ B.T, cell)
        if work is not None and work[0] == k:
            B, lo, grid = work[1]
        h = pl.height_of(pts[cand])
        ij = np.floor((pts[cand] @ B.T - lo) / cell).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < np.array(grid.shape)), axis=1)
        over = np.zeros(len(cand), bool)
        over[inside] = grid[ij[inside, 0], ij[inside, 1]] > 0
        # No upper height limit: a wall or a cupboard must stay one (too large) cluster, not be cut
        # into object-sized pieces.
        ok = over & (h > config.min_height_m) & (h < best_h)
        owner[ok] = k
        best_h[ok] = h[ok]
    boxes_found: list[tuple[float, ObjectBox]] = []
    target = _view_target(scene)
    use = range(len(planes)) if work is None else [work[0]]
    for k in use:
        pl = planes[k]
        sel = cand[owner == k]
        if len(sel) < config.min_cluster_points:
            continue
        sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sel]))
        labels = np.asarray(sub.cluster_dbscan(config.cluster_eps_m, config.cluster_min_points))
        for lab in range(labels.max() + 1 if len(labels) else 0):
            p = pts[sel[labels == lab]]
            if len(p) < config.min_cluster_points:
                continue
            box = _box_on_plane(p, pl, config)
            if box is None:
                continue
            boxes_found.append((float(np.linalg.norm(box.T_world_box[:3, 3] - target)), _with_support(box, k)))
    if not boxes_found:
        sizes = f"clusters of {100 * config.min_object_size_m:.0f}-{100 * config.max_object_size_m:.0f} cm standing on"
        if work is None:
            raise ObjectReconError(f"{scene.path}: no object found on the {len(planes)} support plane(s) ({sizes} "
                                   "a plane); pass --boxes FILE")
        pl = planes[work[0]]
        raise ObjectReconError(
            f"{scene.path}: no object found on the working plane, the support plane at height "
            f"{float(-pl.offset / (pl.normal @ up)):.2f} m that {work[2]} of {len(_frame_indices(scene, config))} "
            f"frames aim at ({sizes} it; {len(planes)} support plane(s) in all); --all-planes searches every "
            "plane, or pass --boxes FILE")
    boxes_found.sort(key=lambda t: t[0])
    boxes = [ObjectBox(f"object_{j + 1:02d}", b.T_world_box, b.size_m, obj_id=j + 1, support_idx=b.support_idx)
             for j, (_, b) in enumerate(boxes_found)]
    return boxes, planes


def _ransac_plane(p: np.ndarray, dist_m: float, iterations: int, rng: np.random.Generator
                  ) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane with the most points within ``dist_m`` among ``iterations`` planes through random point
    triples: ``(unit normal, offset, inlier indices)``. Seeded and single-threaded, so a scene gives
    the same planes on every run (Open3D's multi-threaded ``segment_plane`` does not)."""
    tri = p[rng.integers(0, len(p), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n, tri = n[ok] / norm[ok, None], tri[ok]
    d = -np.einsum("ij,ij->i", n, tri[:, 0])
    counts = np.zeros(len(n), np.int64)
    for a in range(0, len(n), 64):  # (points, 64) distance blocks bound the memory
        counts[a:a + 64] = np.count_nonzero(np.abs(p @ n[a:a + 64].T + d[a:a + 64]) <= dist_m, axis=0)
    if not len(counts):
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(0, np.int64)
    k = int(np.argmax(counts))
    return n[k], float(d[k]), np.flatnonzero(np.abs(p @ n[k] + d[k]) <= dist_m)


def _fit_plane(p: np.ndarray, up: np.ndarray, pl_points: int) -> SupportPlane:
    """Least-squares plane through points (normal towards ``up``)."""
    c = p.mean(0)
    n = np.linalg.svd(p - c, full_matrices=False)[2][2]
    if n @ up < 0:
        n = -n
    return SupportPlane(n, float(-n @ c), int(pl_points))


def _merge_split_planes(planes: list[SupportPlane], masks: list[np.ndarray], pts: np.ndarray, up: np.ndarray,
                        config: ObjectReconConfig) -> tuple[list[SupportPlane], list[np.ndarray]]:
    """Merge planes that are one surface split by the sequential RANSAC, and refit them.

    A flat surface lying on a voxel border of the fused cloud comes out as two layers one voxel
    apart; RANSAC takes one layer (often tilted to reach other furniture at that height) and then
    the rest as a second plane. Left split, the upper layer owns every point standing on the
    surface and the objects on it are lost with it. A plane whose inliers lie (median) within
    ``merge_dist_m`` of a larger plane, normals within ``max_tilt_deg / 4``, joins it; the union
    is refit by least squares.
    """
    order = np.argsort([-pl.num_points for pl in planes], kind="stable")
    out_planes: list[SupportPlane] = []
    out_masks: list[np.ndarray] = []
    cos_max = np.cos(np.radians(config.max_tilt_deg / 4))
    for k in order:
        pl, m = planes[k], masks[k]
        for g, big in enumerate(out_planes):
            if pl.normal @ big.normal >= cos_max and np.median(np.abs(big.height_of(pts[m]))) <= config.merge_dist_m:
                out_masks[g] = np.concatenate([out_masks[g], m])
                out_planes[g] = _fit_plane(pts[out_masks[g]], up, len(out_masks[g]))
                break
        else:
            out_planes.append(pl)
            out_masks.append(m)
    return out_planes, out_masks


def _working_plane(scene: Scene, planes: Sequence[SupportPlane], masks: Sequence[np.ndarray], pts: np.ndarray,
                   config: ObjectReconConfig) -> tuple[int, tuple, int]:
    """Index, footprint region ``(basis, grid origin, grid)`` and number of aiming frames of the plane
    the capture aims at: each frame's aim (the median depth of its central 20 % window, unprojected)
    that lies over a plane's footprint, at most ``max_object_size_m`` above it, votes for the plane
    with the weight 1/z^2; the plane with the largest sum wins."""
    cell = 2 * config.seg_voxel_m
    grids = []
    for pl, m in zip(planes, masks):
        B = _plane_basis(pl.normal)
        lo, grid = _footprint(pts[m] @ B.T, cell)
        grids.append((B, lo, grid))
    votes = np.zeros(len(planes))
    hits: list[list[tuple[tuple[int, int], float]]] = [[] for _ in planes]
    for i in _frame_indices(scene, config):
        K = scene.intrinsics[i]
        d = _depth(scene, i, config)
        h, w = d.shape
        win = d[int(0.4 * h):int(0.6 * h), int(0.4 * w):int(0.6 * w)]
        win = win[win > 0]
        if not len(win):
            continue
        z = float(np.median(win))
        p = transform_points(scene.T_world_cam[i], np.array([[(0.5 * w - K.cx) / K.fx * z, (0.5 * h - K.cy) / K.fy * z, z]]))[0]
        best, best_h = -1, np.inf
        for k, (pl, (B, lo, grid)) in enumerate(zip(planes, grids)):
            hk = float(pl.height_of(p))
            ij = np.floor((p @ B.T - lo) / cell).astype(np.int64)
            if not (np.all(ij >= 0) and np.all(ij < grid.shape) and grid[ij[0], ij[1]]):
                continue
            if -config.plane_dist_m <= hk <= config.max_object_size_m and hk < best_h:
                best, best_h, best_ij = k, hk, (int(ij[0]), int(ij[1]))
        if best >= 0:
            # A vote weighs 1/z^2: the image area a surface patch covers falls with the square of
            # its distance. An object capture moves in close to its objects; the room around them
            # (walls, the floor by the walls) is passed at a distance.
            votes[best] += 1.0 / z ** 2
            hits[best].append((best_ij, 1.0 / z ** 2))
    k = int(np.argmax(votes)) if votes.max() > 0 else int(np.argmax([pl.num_points for pl in planes]))
    # Of that plane, only the connected footprint region most aims land on (the table, not a
    # sideboard at the same height).
    import cv2

    B, lo, grid = grids[k]
    n, lab = cv2.connectedComponents(grid.astype(np.uint8), connectivity=8)
    if hits[k]:
        c = np.bincount([lab[i, j] for (i, j), _ in hits[k]], [w for _, w in hits[k]], minlength=n)
        c[0] = 0
        comp = int(np.argmax(c)) if c.max() > 0 else 0
        if comp > 0:
            grid = (lab == comp).astype(np.uint8)
    return k, (B, lo, grid), len(hits[k])


def _with_support(box: ObjectBox, k: int) -> ObjectBox:
    from dataclasses import replace

    return replace(box, support_idx=k)


def _view_target(scene: Scene) -> np.ndarray:
    """Point closest to all optical axes (least squares): what the capture looks at."""
    c = scene.T_world_cam[:, :3, 3]
    d = scene.T_world_cam[:, :3, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ci, di in zip(c, d):
        P = np.eye(3) - np.outer(di, di)
        A += P
        b += P @ ci
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return c.mean(0)


def _box_on_plane(p: np.ndarray, pl: SupportPlane, config: ObjectReconConfig) -> ObjectBox | None:
    h = pl.height_of(p)
    if h.min() > config.touch_m:
        return None  # floating: not standing on this plane (an overhang, a shelf above)
    B = _plane_basis(pl.normal)
    xy = p @ B.T
    c = xy.mean(0)
    w, V = np.linalg.eigh(np.cov((xy - c).T))
    ax = V[:, ::-1]  # major axis first
    e1 = ax[:, 0] @ B
    e2 = np.cross(pl.normal, e1)
    R = np.stack([e1, e2, pl.normal], axis=1)
    q = (p - p.mean(0)) @ R
    lo, hi = q.min(0), q.max(0)
    size = hi - lo
    if size.max() > config.max_object_size_m or size.max() < config.min_object_size_m:
        return None
    m = config.box_margin_m
    # Bottom: just above the plane's inlier band; top and sides: margin.
    p0 = p.mean(0)
    foot = p0 - pl.height_of(p0) * pl.normal  # p0 projected on the plane
    z_lo = 0.5 * config.min_height_m
    z_hi = float(h.max()) + m
    lo_xy, hi_xy = lo[:2] - m, hi[:2] + m
    centre_local = np.array([0.5 * (lo_xy[0] + hi_xy[0]), 0.5 * (lo_xy[1] + hi_xy[1])])
    centre = foot + R[:, :2] @ centre_local + R[:, 2] * (0.5 * (z_lo + z_hi))
    # (foot differs from p0 only along the normal, so the in-plane offsets above apply to it.)
    size_box = np.array([hi_xy[0] - lo_xy[0], hi_xy[1] - lo_xy[1], z_hi - z_lo])
    return ObjectBox("", make_pose(R, centre), size_box)


def read_boxes_json(path: str | Path) -> list[ObjectBox]:
    """User boxes, world frame, metres::

        {"boxes": [{"name": "mug", "obj_id": 1, "center": [x, y, z], "size": [sx, sy, sz],
                    "R": [[...3x3...]] | "yaw_deg": 30, "symmetric": false}]}

    ``obj_id`` (default: position + 1), ``R``/``yaw_deg`` (default: world axes; yaw about world z)
    and ``symmetric`` are optional. Overlapping boxes are refused.
    """

    path = Path(path)
    items = read_json_items(path, "boxes", "boxes file", "box")
    boxes = []
    for k, it in enumerate(items):
        where = f"{path}: boxes[{k}]"
        if not isinstance(it, dict) or "center" not in it or "size" not in it:
            raise ValueError(f"{where}: needs 'center' [x, y, z] and 'size' [sx, sy, sz] (metres)")
        c = np.asarray(it["center"], dtype=np.float64)
        s = np.asarray(it["size"], dtype=np.float64)
        if c.shape != (3,) or s.shape != (3,) or not np.all(s > 0) or not np.all(np.isfinite(c)):
            raise ValueError(f"{where}: center must be 3 numbers and size 3 positive numbers")
        if "R" in it:
            R = np.asarray(it["R"], dtype=np.float64)
            if R.shape != (3, 3) or abs(np.linalg.det(R) - 1) > 1e-3 or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
                raise ValueError(f"{where}: R must be a 3x3 rotation matrix")
        else:
            a = np.radians(float(it.get("yaw_deg", 0.0)))
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        obj_id = int(it.get("obj_id", k + 1))
        if obj_id < 1:
            raise ValueError(f"{where}: obj_id must be >= 1")
        boxes.append(ObjectBox(str(it.get("name", f"object_{obj_id:02d}")), make_pose(R, c), s, obj_id=obj_id,
                               symmetric=bool(it.get("symmetric", False))))
    ids = [b.obj_id for b in boxes]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{path}: obj_id values must be unique, got {ids}")
    check_boxes_disjoint(boxes, str(path))
    return boxes


def boxes_overlap(a: ObjectBox, b: ObjectBox, tol_m: float = 1e-6) -> bool:
    """Whether two oriented boxes intersect (separating axis test, 15 axes)."""
    Ra, Rb = a.T_world_box[:3, :3], b.T_world_box[:3, :3]
    ha, hb = 0.5 * np.asarray(a.size_m), 0.5 * np.asarray(b.size_m)
    t = b.T_world_box[:3, 3] - a.T_world_box[:3, 3]
    axes = [Ra[:, i] for i in range(3)] + [Rb[:, i] for i in range(3)]
    axes += [np.cross(Ra[:, i], Rb[:, j]) for i in range(3) for j in range(3)]
    for L in axes:
        n = np.linalg.norm(L)
        if n < 1e-9:
            continue
        L = L / n
        ra = np.sum(ha * np.abs(Ra.T @ L))
        rb = np.sum(hb * np.abs(Rb.T @ L))
        if abs(t @ L) > ra + rb - tol_m:
            return False
    return True


def check_boxes_disjoint(boxes: Sequence[ObjectBox], where: str) -> None:
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            if boxes_overlap(boxes[i], boxes[j]):
                raise ValueError(f"{where}: boxes '{boxes[i].name}' and '{boxes[j].name}' overlap; "
                                 "each object needs its own box")


# ---- 2. reconstruction (Algorithm 3) -------------------------------------------------------------

def _visibility_counts(scene: Scene, frames: Sequence[int], pts: np.ndarray, depths: dict,
                       config: ObjectReconConfig) -> tuple[np.ndarray, np.ndarray]:
    """Frames seeing each point (depth agrees within view_tol_m) and the sum of unit vectors from the
    point to those cameras (orients the normals)."""
    count = np.zeros(len(pts), np.int32)
    towards = np.zeros((len(pts), 3))
    for i in frames:
        K = scene.intrinsics[i]
        T_cam_world = invert(scene.T_world_cam[i])
        pc = transform_points(T_cam_world, pts)
        z = pc[:, 2]
        front = z > 0.05
        u = np.full(len(pts), -1, np.int64)
        v = np.full(len(pts), -1, np.int64)
        u[front] = np.floor(K.fx * pc[front, 0] / z[front] + K.cx + 0.5).astype(np.int64)
        v[front] = np.floor(K.fy * pc[front, 1] / z[front] + K.cy + 0.5).astype(np.int64)
        ok = front & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        if not ok.any():
            continue
        d = depths[i][v[ok], u[ok]]
        seen = (d > 0) & (np.abs(d - z[ok]) <= config.view_tol_m)
        idx = np.flatnonzero(ok)[seen]
        count[idx] += 1
        cvec = scene.T_world_cam[i][:3, 3][None, :] - pts[idx]
        towards[idx] += cvec / np.linalg.norm(cvec, axis=1, keepdims=True)
    return count, towards


def _box_owner(boxes: Sequence[ObjectBox], p: np.ndarray) -> np.ndarray:
    """Index of the box each point is in (-1: none); a point in several (found boxes touch when
    objects stand close) goes to the one it is deepest in (smallest normalised inf-norm)."""
    best = np.full(len(p), np.inf)
    owner = np.full(len(p), -1)
    for k, b in enumerate(boxes):
        q = transform_points(invert(b.T_world_box), p.astype(np.float64))
        r = np.max(np.abs(q) / (0.5 * np.asarray(b.size_m)), axis=1)
        sel = (r <= 1.0) & (r < best)
        owner[sel] = k
        best[sel] = r[sel]
    return owner


def _merge_voxels(p: np.ndarray, c: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    key = np.floor(p / voxel).astype(np.int64)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    n = len(cnt)
    ps = np.zeros((n, 3))
    cs = np.zeros((n, 3))
    np.add.at(ps, inv, p)
    np.add.at(cs, inv, c.astype(np.float64))
    return ps / cnt[:, None], np.clip(np.rint(cs / cnt[:, None]), 0, 255).astype(np.uint8)


def reconstruct_objects(scene: Scene, boxes: Sequence[ObjectBox], support: Sequence[SupportPlane] = (),
                        config: ObjectReconConfig = ObjectReconConfig(),
                        strict: bool = True) -> tuple[list[ReconstructedObject], list[str]]:
    """Reconstruct one object per box (thesis Algorithm 3; see the module docstring).

    Args:
        scene: the capture (poses in its world frame).
        boxes: object boxes (user boxes are disjoint; where found boxes touch, a point belongs to
            the box it is deepest in).
        support: planes the boxes' ``support_idx`` refer to (bottom caps of the meshes).
        config: see :class:`ObjectReconConfig`.
        strict: raise :class:`ObjectReconError` when an object cannot be made (seen in too few views,
            too few points); False = skip it and say why in the returned messages (found boxes).

    Returns:
        ``(objects, problems)``.
    """
    import open3d as o3d

    if not boxes:
        raise ObjectReconError("no object boxes given")
    frames = _frame_indices(scene, config)
    t0 = time.perf_counter()
    cand_p: list[list[np.ndarray]] = [[] for _ in boxes]
    cand_c: list[list[np.ndarray]] = [[] for _ in boxes]
    seen_frames = np.zeros(len(boxes), np.int32)
    depths: dict[int, np.ndarray] = {}
    corners = np.concatenate([b.corners() for b in boxes])
    aabb_lo, aabb_hi = corners.min(0), corners.max(0)
    for i in progress(frames, desc="objects: candidates", unit="frame"):
        depth = _depth(scene, i, config)
        depths[i] = depth
        color = scene.frames.load(i)[0]
        p, mask = unproject_depth(scene.intrinsics[i], depth, scene.T_world_cam[i], stride=config.stride)
        if not len(p):
            continue
        rgb = color[::config.stride, ::config.stride][mask]
        near = np.all((p >= aabb_lo) & (p <= aabb_hi), axis=1)  # cheap cull before the box tests
        p, rgb = p[near], rgb[near]
        owner = _box_owner(boxes, p)
        for k, b in enumerate(boxes):
            inside = owner == k
            if np.count_nonzero(inside) >= 20:
                seen_frames[k] += 1
                cand_p[k].append(p[inside].astype(np.float64))
                cand_c[k].append(rgb[inside])
    t_cand = time.perf_counter() - t0

    out: list[ReconstructedObject] = []
    problems: list[str] = []

    def fail(msg: str) -> None:
        if strict:
            raise ObjectReconError(msg)
        problems.append(msg)

    for k, b in enumerate(progress(boxes, desc="objects: reconstruct", unit="object")):
        if seen_frames[k] <= config.min_views:
            fail(f"object '{b.name}': seen in {seen_frames[k]} frame(s), needs more than {config.min_views}")
            continue
        p, c = _merge_voxels(np.concatenate(cand_p[k]), np.concatenate(cand_c[k]), config.voxel_m)
        views, towards = _visibility_counts(scene, frames, p, depths, config)
        keep = views > config.min_views
        p, c, views, towards = p[keep], c[keep], views[keep], towards[keep]
        if len(p) < config.min_object_points:
            fail(f"object '{b.name}': {len(p)} points seen in more than {config.min_views} views "
                 f"(needs {config.min_object_points})")
            continue
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        _, ind = pc.remove_statistical_outlier(config.sor_neighbors, config.sor_std_ratio)
        ind = np.asarray(ind)
        p, c, views, towards = p[ind], c[ind], views[ind], towards[ind]
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=config.normal_radius_m, max_nn=30))
        n = np.asarray(pc.normals)
        flip = np.sum(n * towards, axis=1) < 0
        n[flip] *= -1

        # Object frame: the box's axes, origin at the centre of the points' extent in them.
        R = b.T_world_box[:3, :3]
        q = p @ R
        centre = R @ (0.5 * (q.min(0) + q.max(0)))
        T_world_obj = make_pose(R, centre)
        T_obj_world = invert(T_world_obj)
        p_obj = transform_points(T_obj_world, p)
        n_obj = n @ R
        obj = ReconstructedObject(
            obj_id=int(b.obj_id if b.obj_id is not None else k + 1), name=b.name, T_world_obj=T_world_obj,
            points_m=p_obj.astype(np.float32), colors=c, normals=n_obj.astype(np.float32),
            views=views.astype(np.int32), symmetric=b.symmetric, frames_seen=int(seen_frames[k]))
        plane = support[b.support_idx] if b.support_idx is not None and b.support_idx < len(support) else None
        _mesh(obj, plane, T_obj_world, config)
        obj.stats.update({"points": int(len(p)), "frames_seen": int(seen_frames[k]),
                     "median_views": float(np.median(views)), "watertight": bool(obj.watertight),
                     "extent_m": [round(float(x), 4) for x in (p_obj.max(0) - p_obj.min(0))]})
        out.append(obj)
    if not out:
        raise ObjectReconError(f"{scene.path}: no object could be reconstructed ({'; '.join(problems)})")
    ids = [o.obj_id for o in out]
    if len(set(ids)) != len(ids):
        raise ObjectReconError(f"object ids must be unique, got {ids}")
    for o in out:
        o.stats["seconds_candidates_total"] = round(t_cand, 2)
    return out, problems


def _mesh(obj: ReconstructedObject, plane: SupportPlane | None, T_obj_world: np.ndarray,
          config: ObjectReconConfig) -> None:
    """Poisson mesh of the cloud, closed at the bottom by the support plane; kept when watertight
    and faithful to the cloud."""
    import open3d as o3d

    p, n, c = obj.points_m.astype(np.float64), obj.normals.astype(np.float64), obj.colors
    if plane is not None:
        # Bottom cap: the object's footprint on its plane (the plane hides the object's bottom from
        # every camera; the object stands on it), normals pointing down.
        n_obj = T_obj_world[:3, :3] @ plane.normal
        # n.(R p_obj + t) + d = 0  =>  (R^T n).p_obj + (n.t + d) = 0
        d_obj = plane.offset + plane.normal @ invert(T_obj_world)[:3, 3]
        h = p @ n_obj + d_obj
        low = p[h < 3 * config.min_height_m]
        if len(low) >= 3:
            cap = _fill_footprint(p - h[:, None] * n_obj[None, :], n_obj, spacing=config.voxel_m * 1.5)
            if len(cap):
                p = np.concatenate([p, cap])
                n = np.concatenate([n, np.repeat(-n_obj[None, :], len(cap), 0)])
                c = np.concatenate([c, np.repeat(np.median(obj.colors, 0)[None, :].astype(np.uint8), len(cap), 0)])
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    pc.normals = o3d.utility.Vector3dVector(n)
    pc.colors = o3d.utility.Vector3dVector(c.astype(np.float64) / 255.0)
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=config.poisson_depth)
    except RuntimeError:
        return
    dens = np.asarray(dens)
    obj.stats["poisson_watertight_untrimmed"] = bool(mesh.is_watertight())
    # Poisson closes the surface far from the data where nothing was seen; vertices with a low
    # sample density there are cut (the mesh then may have holes: watertight is checked after).
    mesh.remove_vertices_by_mask(dens < np.quantile(dens, config.poisson_trim_quantile))
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_vertices()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        return
    v = np.asarray(mesh.vertices)
    dev = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v)).compute_point_cloud_distance(pc))
    watertight = bool(mesh.is_watertight())
    obj.stats["poisson_watertight"] = watertight
    obj.stats["mesh_dev_p99_m"] = round(float(np.quantile(dev, 0.99)), 4)
    if np.quantile(dev, 0.99) > config.mesh_max_dev_m:
        return  # not faithful to the data: the cloud stays the model
    obj.mesh_vertices = v.astype(np.float32)
    obj.mesh_faces = np.asarray(mesh.triangles).astype(np.int32)
    vc = np.asarray(mesh.vertex_colors)
    obj.mesh_colors = (np.clip(vc, 0, 1) * 255).round().astype(np.uint8) if len(vc) == len(v) else None
    obj.watertight = watertight


def _fill_footprint(proj: np.ndarray, n: np.ndarray, spacing: float) -> np.ndarray:
    """Grid points (``spacing``) filling the 2D convex hull of points projected on a plane."""
    from scipy.spatial import ConvexHull, QhullError
    from matplotlib.path import Path as MplPath

    B = _plane_basis(n)
    xy = proj @ B.T
    try:
        hull = ConvexHull(xy)
    except (QhullError, ValueError):
        return np.zeros((0, 3))
    poly = MplPath(xy[hull.vertices])
    lo, hi = xy.min(0), xy.max(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    g = g[poly.contains_points(g)]
    base = float(np.median(proj @ n))
    return g @ B + base * n[None, :]


# ---- 3. writing into the scene -------------------------------------------------------------------

def write_objects_into_scene(scene_path: str | Path, objects: Sequence[ReconstructedObject]) -> list[dict]:
    """Store reconstructed objects in the saved scene at ``scene_path`` (see the module docstring).

    Per object: ``objects/recon-<run>/obj_XXXXXX.ply`` (the model: watertight mesh, else the cloud)
    and ``obj_XXXXXX_points.ply`` (the cloud: colour, normals), metres, object frame. Returns the
    new ``scene.json`` object entries. Nothing changes in the scene unless all of it is written.
    """

    scene_path = Path(scene_path)
    hdr_path = scene_path / "scene.json"
    if not hdr_path.is_file():
        raise SceneError(f"{scene_path}: not a PreSim scene (no scene.json)")
    hdr = json.loads(hdr_path.read_text())
    run = time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:6]
    rel_dir = f"objects/recon-{run}"
    final = scene_path / rel_dir
    staging = scene_path / "objects" / f".recon-{run}.partial"
    staging.mkdir(parents=True)
    entries = []
    try:
        for o in objects:
            base = f"obj_{o.obj_id:06d}"
            write_ply(staging / f"{base}_points.ply", o.points_m, np.zeros((0, 3), np.int32), colors=o.colors,
                      normals=o.normals)
            if o.mesh_vertices is not None:
                write_ply(staging / f"{base}.ply", o.mesh_vertices, o.mesh_faces, colors=o.mesh_colors)
                model = f"{rel_dir}/{base}.ply"
            else:
                # Point models as 'x y z' text: what load_model reads for point clouds (the PLY
                # beside it keeps colour and normals).
                np.savetxt(staging / f"{base}.xyz", o.points_m, fmt="%.6f")
                model = f"{rel_dir}/{base}.xyz"
            entries.append({
                "obj_id": int(o.obj_id), "name": o.name, "T_world_obj": np.asarray(o.T_world_obj).tolist(),
                "model_path": model, "symmetric": bool(o.symmetric),
                "points_path": f"{rel_dir}/{base}_points.ply", "reconstructed": True,
                "has_mesh": o.mesh_vertices is not None, "watertight": bool(o.watertight), "num_points": int(len(o.points_m)),
                "frames_seen": int(o.frames_seen),
            })
        os.replace(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    old = hdr.get("objects", [])
    hdr["objects"] = entries
    if old:
        prev = [e for e in old if not e.get("reconstructed")]
        if prev:
            hdr["objects_replaced"] = prev  # e.g. the sample scene's true objects, files kept
    try:
        atomic_write_json(hdr_path, hdr, indent=1)  # the commit point
    except BaseException:
        shutil.rmtree(final, ignore_errors=True)
        raise
    # Earlier reconstructions are no longer referenced.
    for d in (scene_path / "objects").glob("recon-*"):
        if d.name != final.name and d.is_dir():
            shutil.rmtree(d, ignore_errors=True)
    return entries
