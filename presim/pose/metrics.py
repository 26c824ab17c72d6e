"""6D pose error functions: numpy reference with bop_toolkit's names and meanings.

Source of truth: bop_toolkit ``bop_toolkit_lib/pose_error.py`` and ``misc.py``. Same definitions,
units follow the inputs (the project passes metres; ``re`` returns degrees):

- ``add``   ADD, mean distance of corresponding model points (Hinterstoisser ACCV'12; thesis eq. 6.1).
- ``adi``   ADD-S, mean distance from each GT-posed point to the nearest estimate-posed point
            (KD-tree, as bop_toolkit; thesis eq. 6.2).
- ``add_s`` ADD(-S): ``adi`` for symmetric objects, ``add`` otherwise (bop_toolkit's "ad").
- ``proj``  mean 2D distance of projected model points, pixels (Brachmann CVPR'16).
- ``re``, ``te``  rotation error (degrees) and translation error.
- ``mssd``, ``mspd``  BOP'19 maximum symmetry-aware surface / projection distances.
- ``vsd``   BOP visible surface discrepancy (needs a test depth map and a depth renderer).

Poses are ``R`` (3, 3) and ``t`` (3,) mapping model to camera (``x_cam = R x + t``), i.e. T_cam_obj.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from presim.geometry import Intrinsics, invert, make_pose

__all__ = [
    "transform_pts",
    "project_pts",
    "add",
    "adi",
    "add_s",
    "proj",
    "re",
    "te",
    "mssd",
    "mspd",
    "vsd",
    "depth_to_dist",
    "estimate_visib_mask",
    "symmetry_transformations",
    "check_pose",
    "MeshDepthRenderer",
]


def check_pose(R: np.ndarray, t: np.ndarray, what: str = "pose") -> tuple[np.ndarray, np.ndarray]:
    """Shapes/finiteness check at the public border; returns float64 copies."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"{what}: expected R (3, 3) and t (3,), got {R.shape} and {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"{what}: contains non-finite values")
    return R, t


def _check_pts(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"model points must be (N, 3) with N > 0, got {pts.shape}")
    return pts


def _K(K) -> np.ndarray:
    return K.K if isinstance(K, Intrinsics) else np.asarray(K, dtype=np.float64).reshape(3, 3)


def transform_pts(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) points -> ``R @ p + t`` (N, 3)."""
    return pts @ np.asarray(R).T + np.asarray(t).reshape(1, 3)


def project_pts(pts: np.ndarray, K, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Project model points (N, 3) posed by (R, t) with camera matrix K -> (N, 2) pixels.

    Pixel (0, 0) is the centre of the top-left pixel (project convention; same formula as BOP).
    """
    p = transform_pts(pts, R, t) @ _K(K).T
    return p[:, :2] / p[:, 2:3]


def add(R_est, t_est, R_gt, t_gt, pts) -> float:
    """ADD: mean ||(R_e x + t_e) - (R_g x + t_g)|| over model points ``pts`` (N, 3)."""
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    return float(np.linalg.norm(transform_pts(pts, R_est, t_est) - transform_pts(pts, R_gt, t_gt), axis=1).mean())


def adi(R_est, t_est, R_gt, t_gt, pts) -> float:
    """ADD-S: mean over GT-posed points of the distance to the nearest estimate-posed point."""
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    # Nearest neighbours from vertices in the GT pose to vertices in the estimated pose (as BOP).
    nn_dists, _ = cKDTree(transform_pts(pts, R_est, t_est)).query(transform_pts(pts, R_gt, t_gt), k=1)
    return float(nn_dists.mean())


def add_s(R_est, t_est, R_gt, t_gt, pts, symmetric: bool) -> float:
    """ADD(-S): ``adi`` when the object is symmetric, else ``add`` (bop_toolkit's ``ad``)."""
    return adi(R_est, t_est, R_gt, t_gt, pts) if symmetric else add(R_est, t_est, R_gt, t_gt, pts)


def proj(R_est, t_est, R_gt, t_gt, K, pts) -> float:
    """Mean 2D reprojection error (pixels) of the model points. ``K``: 3x3 or Intrinsics."""
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    return float(np.linalg.norm(project_pts(pts, K, R_est, t_est) - project_pts(pts, K, R_gt, t_gt), axis=1).mean())


def re(R_est, R_gt) -> float:
    """Rotation error in degrees: angle of ``R_est R_gt^-1``."""
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    if R_est.shape != (3, 3) or R_gt.shape != (3, 3):
        raise ValueError(f"re: expected two 3x3 rotations, got {R_est.shape} and {R_gt.shape}")
    c = float(0.5 * (np.trace(R_est @ np.linalg.inv(R_gt)) - 1.0))
    # Avoid invalid values due to numerical errors.
    c = min(1.0, max(-1.0, c))
    return math.degrees(math.acos(c))


def te(t_est, t_gt) -> float:
    """Translation error ||t_gt - t_est|| (units of t)."""
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(-1)
    if t_est.size != 3 or t_gt.size != 3:
        raise ValueError(f"te: expected two 3-vectors, got {t_est.size} and {t_gt.size}")
    return float(np.linalg.norm(t_gt - t_est))


def symmetry_transformations(symmetries_discrete: Sequence[np.ndarray] = (),
                             symmetries_continuous: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                             max_sym_disc_step: float = 0.01) -> np.ndarray:
    """Symmetry transformations of an object, (S, 4, 4), identity first (bop_toolkit's
    ``misc.get_symmetry_transformations``; translations in the units of the inputs: metres).

    ``symmetries_discrete``: 4x4 transforms; ``symmetries_continuous``: ``(axis (3,), offset (3,))``
    pairs, as :class:`presim.formats.bop.ModelInfo` holds them. The result is the ``syms`` argument
    of :func:`mssd` / :func:`mspd`.

    Continuous symmetries are discretised into ``ceil(pi / max_sym_disc_step)`` rotations so
    that the point farthest from the axis travels at most ``max_sym_disc_step`` x diameter between
    consecutive ones; every discrete symmetry (and the identity) is combined with every step.
    """
    disc = [np.eye(4)]
    cont: list[np.ndarray] = []
    disc += [np.asarray(T, dtype=np.float64) for T in symmetries_discrete]
    for axis, offset in symmetries_continuous:
        offset = np.asarray(offset, dtype=np.float64)
        n = int(np.ceil(np.pi / max_sym_disc_step))
        step = 2.0 * np.pi / n
        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        for i in range(n):  # i = 0 is the identity, as in current bop_toolkit
            ang = i * step
            R = np.eye(3) + np.sin(ang) * Kx + (1 - np.cos(ang)) * (Kx @ Kx)  # Rodrigues
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = -R @ offset + offset  # rotation about the axis through `offset`
            cont.append(T)
    if not cont:
        return np.stack(disc)
    return np.stack([Tc @ Td for Td in disc for Tc in cont])


def _syms(syms) -> np.ndarray:
    s = np.asarray(syms, dtype=np.float64)
    if s.ndim != 3 or s.shape[1:] != (4, 4) or len(s) == 0:
        raise ValueError(f"syms must be (S, 4, 4) with S >= 1 (see symmetry_transformations), got {s.shape}")
    return s


def mssd(R_est, t_est, R_gt, t_gt, pts, syms) -> float:
    """MSSD: min over symmetries S of max_x ||(R_e x + t_e) - (R_g S x + t_g)||."""
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    pts_est = transform_pts(pts, R_est, t_est)
    es = []
    for S in _syms(syms):
        R_s = R_gt @ S[:3, :3]
        t_s = R_gt @ S[:3, 3] + t_gt
        es.append(np.linalg.norm(pts_est - transform_pts(pts, R_s, t_s), axis=1).max())
    return float(min(es))


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> float:
    """MSPD (pixels): min over symmetries of the max 2D distance of projected model points."""
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    proj_est = project_pts(pts, K, R_est, t_est)
    es = []
    for S in _syms(syms):
        R_s = R_gt @ S[:3, :3]
        t_s = R_gt @ S[:3, 3] + t_gt
        es.append(np.linalg.norm(proj_est - project_pts(pts, K, R_s, t_s), axis=1).max())
    return float(min(es))


# ---- VSD --------------------------------------------------------------------------------------

def depth_to_dist(depth: np.ndarray, K) -> np.ndarray:
    """z-depth (H, W) -> distance from the camera centre (H, W), 0 stays 0 (bop's
    ``depth_im_to_dist_im_fast``; pixel (u, v) centre at integer coordinates)."""
    Km = _K(K)
    h, w = depth.shape
    xs = (np.arange(w) - Km[0, 2]) / Km[0, 0]
    ys = (np.arange(h) - Km[1, 2]) / Km[1, 1]
    d = depth.astype(np.float64)
    return np.sqrt((xs[None, :] * d) ** 2 + (ys[:, None] * d) ** 2 + d ** 2)


def estimate_visib_mask(d_test: np.ndarray, d_model: np.ndarray, delta: float,
                        visib_gt: np.ndarray | None = None) -> np.ndarray:
    """BOP'19 visibility mask of a rendered model: model pixels not behind the test surface by more
    than ``delta`` (or where the test depth is missing). With ``visib_gt`` (estimate masks), GT-visible
    pixels covered by the model are added (bop's ``estimate_visib_mask_est``)."""
    diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    visib = np.logical_and(np.logical_or(diff <= delta, d_test == 0), d_model > 0)
    if visib_gt is not None:
        visib = np.logical_or(visib, np.logical_and(visib_gt, d_model > 0))
    return visib


DepthRenderer = Callable[[np.ndarray, np.ndarray, np.ndarray, int, int], np.ndarray]
"""``render(R, t, K (3x3), width, height) -> depth (H, W)`` of the object model (0 = background)."""


def vsd(R_est, t_est, R_gt, t_gt, depth_test: np.ndarray, K, delta: float, taus: Sequence[float],
        normalized_by_diameter: bool, diameter: float, renderer: DepthRenderer,
        cost_type: str = "step") -> list[float]:
    """Visible Surface Discrepancy (Hodan et al. ECCV'18), one error per tau in ``taus``.

    ``depth_test``, ``delta``, ``diameter`` and ``t`` in one length unit (the project: metres; BOP
    uses delta = 15 mm). ``renderer`` renders the model's depth at a pose (see :class:`DepthRenderer`).
    """
    R_est, t_est = check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = check_pose(R_gt, t_gt, "ground truth")
    depth_test = np.asarray(depth_test)
    if depth_test.ndim != 2:
        raise ValueError(f"vsd: depth_test must be (H, W), got {depth_test.shape}")
    h, w = depth_test.shape
    Km = _K(K)
    depth_est = renderer(R_est, t_est, Km, w, h)
    depth_gt = renderer(R_gt, t_gt, Km, w, h)
    dist_test = depth_to_dist(depth_test, Km)
    dist_gt = depth_to_dist(depth_gt, Km)
    dist_est = depth_to_dist(depth_est, Km)
    visib_gt = estimate_visib_mask(dist_test, dist_gt, delta)
    visib_est = estimate_visib_mask(dist_test, dist_est, delta, visib_gt=visib_gt)
    visib_inter = np.logical_and(visib_gt, visib_est)
    visib_union = np.logical_or(visib_gt, visib_est)
    union_count = int(visib_union.sum())
    comp_count = union_count - int(visib_inter.sum())
    dists = np.abs(dist_gt[visib_inter] - dist_est[visib_inter])
    if normalized_by_diameter:
        dists = dists / diameter
    if union_count == 0:
        return [1.0] * len(taus)
    errors = []
    for tau in taus:
        if cost_type == "step":
            costs = dists >= tau
        elif cost_type == "tlinear":  # truncated linear (ECCVW'16 definition)
            costs = np.minimum(dists / tau, 1.0)
        else:
            raise ValueError(f"vsd: unknown cost_type {cost_type!r} (use 'step' or 'tlinear')")
        errors.append(float((np.sum(costs) + comp_count) / float(union_count)))
    return errors


class MeshDepthRenderer:
    """Exact z-depth of a triangle mesh by ray casting (Open3D ``RaycastingScene``), for VSD.

    Args:
        pts: (N, 3) vertices in the model frame (same length unit as the poses).
        faces: (F, 3) triangle indices.
    """

    def __init__(self, pts: np.ndarray, faces: np.ndarray):
        try:
            import open3d as o3d
        except ImportError as e:  # optional extra: presim[mesh]
            raise ImportError("VSD needs open3d (pip install 'presim[mesh]')") from e
        pts = _check_pts(pts)
        faces = np.asarray(faces)
        if faces is None or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"MeshDepthRenderer: faces must be (F, 3) triangles, got {getattr(faces, 'shape', None)}")
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(pts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))

    def __call__(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        Km = _K(K)
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        dirs_cam = np.stack([(u - Km[0, 2]) / Km[0, 0], (v - Km[1, 2]) / Km[1, 1], np.ones_like(u)], -1)
        # Cast in the model frame: origin = the camera centre, direction = R^T d (d has z = 1, so the
        # hit distance along it is the z-depth directly).
        T_model_cam = invert(make_pose(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3)))
        origin = T_model_cam[:3, 3]
        dirs = dirs_cam.reshape(-1, 3) @ T_model_cam[:3, :3].T
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=1).astype(np.float32)
        hit = self._scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy().reshape(height, width)
        depth = np.where(np.isfinite(hit), hit, 0.0).astype(np.float32)
        return depth
