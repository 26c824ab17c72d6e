"""Floor plane and gravity of a captured scene.

How: gravity comes from a given vector or from the cameras (people and robots hold cameras with
little roll: the cameras' x axes are near horizontal and their up axes, -y of ``T_world_cam``, point
roughly against gravity; see :func:`gravity_from_cameras`). Then a
sequential RANSAC finds up to ``max_planes`` large planes in the scene's point cloud whose normals are
within ``max_tilt_deg`` of that up direction; the floor is the *lowest* of them whose inlier patch
covers at least ``min_area_m2`` and lies below the cameras. When found, the world is rotated (smallest
rotation taking the floor normal to +z) and shifted along z so the floor is z = 0; metric scale never
changes. Otherwise (tabletop captures, a shelf bin) the world frame is kept and only the gravity
estimate is stored, with a note saying why.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from presim.capture.scene import FloorPlane, Scene
from presim.geometry import make_pose

__all__ = ["FloorConfig", "FloorResult", "gravity_from_cameras", "estimate_floor", "align_scene_to_floor",
           "rotation_between"]


@dataclass(frozen=True)
class FloorConfig:
    """Parameters of the floor search."""

    dist_thresh_m: float = 0.02
    """RANSAC inlier distance to the plane, metres (depth noise of a consumer sensor at ~2 m)."""
    max_tilt_deg: float = 30.0
    """Largest angle between a candidate plane's normal and the up direction. Camera-based gravity is
    only approximate (cameras pitch down while scanning), hence generous."""
    iterations: int = 300
    """RANSAC hypotheses per plane."""
    sample_radius_m: float = 0.3
    """The 2nd and 3rd point of a hypothesis are drawn within this distance of the 1st."""
    max_planes: int = 6
    """Planes extracted one after another (their inliers removed) before picking the lowest."""
    min_inlier_frac: float = 0.05
    """A candidate plane holds at least this fraction of the point cloud."""
    min_area_m2: float = 1.0
    """A floor's inlier patch covers at least this area (0.1 m grid cells); smaller horizontal planes
    (a shelf bottom, a box, a small table top) are not a floor."""
    min_camera_height_m: float = 0.1
    """The cameras' median height above a floor candidate must be at least this."""
    max_points: int = 100_000
    """Points sub-sampled from the cloud for RANSAC (speed)."""
    seed: int = 0


@dataclass(frozen=True)
class FloorResult:
    """What :func:`estimate_floor` found."""

    floor: FloorPlane | None
    """The floor in the *input* world frame (normal pointing up), or None."""
    gravity_world: np.ndarray
    """Unit gravity in the input world frame (from the floor normal when found, else the estimate)."""
    T_aligned_world: np.ndarray | None
    """Rigid transform to the floor-aligned frame (gravity -z, floor z = 0), None without a floor."""
    note: str
    """Human-readable summary (why no floor, which gravity source)."""


def gravity_from_cameras(T_world_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """Gravity from the camera axes.

    People and robots keep cameras nearly roll-free while pitch varies a lot (scanning a table, looking
    down into a bin). So the cameras' x axes (image right) are close to horizontal: gravity is the
    direction most perpendicular to all of them (smallest eigenvector of ``sum x x^T``), signed by the
    mean up axis (-y). When the x axes do not span the horizontal plane (all cameras face one way),
    the mean up axis made perpendicular to the mean x axis is used instead.

    Args:
        T_world_cam: (N, 4, 4) camera-to-world poses (OpenCV cameras: y down).

    Returns:
        ``(gravity_world unit (3,), consistency)`` where consistency in [0, 1] is the length of the
        mean up vector (1 = all cameras equally oriented; near 0 = little information).
    """
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    up = -T[:, :3, 1]  # camera -y axis in the world
    xs = T[:, :3, 0]
    m = up.mean(axis=0)
    cons = float(np.linalg.norm(m))
    if cons < 1e-9:
        return np.array([0.0, 0.0, -1.0]), 0.0
    w, V = np.linalg.eigh(xs.T @ xs / len(xs))
    if w[1] > 0.05:  # x axes spread over a plane: its normal is the vertical
        g = V[:, 0]
        g = g if g @ m < 0 else -g
    else:
        xm = xs.mean(axis=0)
        xm /= np.linalg.norm(xm)
        g = -(m - (m @ xm) * xm)
    return g / np.linalg.norm(g), cons


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3x3) taking unit vector ``a`` to unit vector ``b``."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: rotate by pi about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _fit_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[-1]
    return n, float(-n @ c)


def _patch_area_m2(p: np.ndarray, n: np.ndarray, cell_m: float = 0.1) -> float:
    R = rotation_between(n, np.array([0.0, 0.0, 1.0]))
    q = p @ R.T
    cells = np.unique(np.floor(q[:, :2] / cell_m).astype(np.int64), axis=0)
    return float(len(cells) * cell_m * cell_m)


def estimate_floor(xyz: np.ndarray, T_world_cam: np.ndarray, gravity: np.ndarray | None = None,
                   config: FloorConfig = FloorConfig()) -> FloorResult:
    """Find the floor of a point cloud.

    Args:
        xyz: (M, 3) world points, metres.
        T_world_cam: (N, 4, 4) camera poses (for the up direction and the "below the cameras" test).
        gravity: (3,) gravity direction in the world frame when known (any length), else estimated.
        config: thresholds.

    Returns:
        :class:`FloorResult`.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be (M, 3), got {xyz.shape}")
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    if gravity is not None:
        g = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-9:
            raise ValueError(f"gravity must be a finite non-zero vector, got {g}")
        g = g / np.linalg.norm(g)
        g_src = "given gravity"
    else:
        g, cons = gravity_from_cameras(T_world_cam)
        g_src = f"gravity from camera up axes (consistency {cons:.2f})"
    up = -g
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if len(xyz) < 3:
        return FloorResult(None, g, None, f"no floor: point cloud too small; {g_src}")

    rng = np.random.default_rng(config.seed)
    if len(xyz) > config.max_points:
        xyz = xyz[rng.choice(len(xyz), config.max_points, replace=False)]
    total = len(xyz)
    cos_tilt = np.cos(np.radians(config.max_tilt_deg))
    cams = T_world_cam[:, :3, 3]
    remaining = xyz
    candidates: list[tuple[float, FloorPlane, float, float]] = []  # (height along up, plane, area, cam h)
    rejected: list[str] = []
    for _ in range(config.max_planes):
        if len(remaining) < max(3, config.min_inlier_frac * total):
            break
        best_count, best = 0, None
        # Local sampling: the 2nd and 3rd points come from within sample_radius_m of the 1st, so a
        # plane holding 10 % of a cluttered room is hit in ~8 % of the hypotheses instead of 0.1 %.
        tree = cKDTree(remaining)
        seeds = rng.integers(0, len(remaining), size=config.iterations)
        for i0 in seeds:
            a = remaining[i0]
            near = tree.query_ball_point(a, config.sample_radius_m)
            if len(near) < 3:
                continue
            i1, i2 = rng.choice(len(near), 2, replace=False)
            b, c = remaining[near[i1]], remaining[near[i2]]
            n = np.cross(b - a, c - a)
            nn = np.linalg.norm(n)
            # A sliver triangle has an unreliable normal.
            if nn < 0.1 * config.sample_radius_m ** 2:
                continue
            n /= nn
            if abs(n @ up) < cos_tilt:
                continue
            count = int(np.count_nonzero(np.abs((remaining - a) @ n) < config.dist_thresh_m))
            if count > best_count:
                best_count, best = count, (n, float(-n @ a))
        if best is None or best_count < config.min_inlier_frac * total:
            break
        n, d = best
        inl = np.abs(remaining @ n + d) < config.dist_thresh_m
        n, d = _fit_plane(remaining[inl])  # least-squares refit on the inliers
        # Second refit on a tighter band: clutter standing on the plane stops pulling it.
        tight = np.abs(remaining @ n + d) < 0.5 * config.dist_thresh_m
        if tight.sum() >= 3:
            n, d = _fit_plane(remaining[tight])
        inl = np.abs(remaining @ n + d) < config.dist_thresh_m
        if n @ up < 0:
            n, d = -n, -d
        pts = remaining[inl]
        remaining = remaining[~inl]
        if abs(n @ up) < cos_tilt:
            continue
        area = _patch_area_m2(pts, n)
        cam_h = float(np.median(cams @ n + d))
        plane = FloorPlane(tuple(float(x) for x in n), float(d), float(inl.sum() / total))
        h = float(np.median(pts @ up))
        if area < config.min_area_m2:
            rejected.append(f"plane with {plane.inlier_frac:.0%} of points covers only {area:.2f} m^2")
            continue
        if cam_h < config.min_camera_height_m:
            rejected.append(f"plane with {plane.inlier_frac:.0%} of points is not below the cameras")
            continue
        candidates.append((h, plane, area, cam_h))
    if not candidates:
        why = "; ".join(rejected) if rejected else "no large plane perpendicular to gravity"
        return FloorResult(None, g, None, f"no floor found ({why}): world frame kept; {g_src}")
    h, plane, area, cam_h = min(candidates, key=lambda c: c[0])
    n = np.asarray(plane.normal)
    R = rotation_between(n, np.array([0.0, 0.0, 1.0]))
    # After the rotation the floor is z + d = 0; shifting by +d along z puts it at z = 0.
    T = make_pose(R, np.array([0.0, 0.0, plane.offset]))
    note = (f"floor found: {plane.inlier_frac:.0%} of points, {area:.1f} m^2, cameras {cam_h:.2f} m above it, "
            f"normal {np.degrees(np.arccos(np.clip(n @ up, -1, 1))):.1f} deg from the {g_src}")
    return FloorResult(plane, -n, T, note)


def align_scene_to_floor(scene: Scene, gravity: np.ndarray | None = None,
                         config: FloorConfig = FloorConfig()) -> Scene:
    """The scene in a floor-aligned world (gravity -z, floor z = 0) when a floor is found, else the
    same world with ``gravity_world`` set and a note. Needs ``scene.points``."""
    if scene.points is None:
        raise ValueError("align_scene_to_floor needs the scene's point cloud (store.fuse_point_cloud)")
    res = estimate_floor(scene.points.xyz, scene.T_world_cam, gravity, config)
    if res.floor is None:
        return replace(scene, gravity_world=res.gravity_world,
                       meta=replace(scene.meta, notes=scene.meta.notes + (res.note,)))
    s = replace(scene, floor=res.floor, gravity_world=res.gravity_world,
                meta=replace(scene.meta, notes=scene.meta.notes + (res.note,)))
    out = s.transformed(res.T_aligned_world, "floor_alignment")
    # Exact values after alignment (the transform leaves ~1e-16 residue).
    return replace(out, gravity_world=np.array([0.0, 0.0, -1.0]),
                   floor=FloorPlane((0.0, 0.0, 1.0), 0.0, res.floor.inlier_frac))
