"""Quality of reconstructed objects against known meshes (the sample scene; any scene whose
``scene.json`` kept the true objects under ``objects_replaced``).

- **accuracy**: mean distance from reconstructed points to the true mesh surface (exact, Open3D).
- **completion**: mean distance from the true *visible* surface to the reconstruction.
- **chamfer** = (accuracy + completion) / 2.
- **completeness**: fraction of the true visible surface within ``threshold_m`` of the reconstruction.
  The visible surface: area-uniform samples of the true mesh that the capture's exact depth sees
  (within 3 mm) in at least ``min_views`` frames.
- **mask IoU**: visible masks of the real split vs the sample scene's exact object-id images.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from presim.datasets.object_sources import PlacedObject
from presim.geometry import invert, transform_points

__all__ = ["sample_surface", "visible_samples", "surface_metrics", "match_objects", "real_split_mask_ious"]


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) area-uniform points on a triangle mesh."""
    rng = np.random.default_rng(seed)
    tri = vertices[faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = rng.choice(len(tri), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = 1 - s, s * (1 - r2), s * r2
    t = tri[k]
    return a[:, None] * t[:, 0] + b[:, None] * t[:, 1] + c[:, None] * t[:, 2]


def visible_samples(pts_world: np.ndarray, T_world_cam: np.ndarray, intrinsics, depth_exact, tol_m: float = 0.003
                    ) -> np.ndarray:
    """(P,) number of frames whose exact depth sees each point."""
    count = np.zeros(len(pts_world), np.int32)
    for i in range(len(T_world_cam)):
        K = intrinsics[i]
        pc = transform_points(invert(T_world_cam[i]), pts_world)
        z = pc[:, 2]
        ok = z > 0.05
        u = np.full(len(z), -1)
        v = np.full(len(z), -1)
        u[ok] = np.floor(K.fx * pc[ok, 0] / z[ok] + K.cx + 0.5).astype(int)
        v[ok] = np.floor(K.fy * pc[ok, 1] / z[ok] + K.cy + 0.5).astype(int)
        ok &= (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        d = np.asarray(depth_exact[i])
        idx = np.flatnonzero(ok)
        seen = np.abs(d[v[idx], u[idx]] - z[idx]) <= tol_m
        count[idx[seen]] += 1
    return count


def surface_metrics(recon_world: np.ndarray, true_vertices_world: np.ndarray, true_faces: np.ndarray,
                    visible_true: np.ndarray, threshold_m: float = 0.005) -> dict:
    """Accuracy, completion, chamfer (metres) and completeness of one object (see the module doc)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(true_vertices_world.astype(np.float32)),
                     o3d.core.Tensor(true_faces.astype(np.uint32)))
    acc = rc.compute_distance(o3d.core.Tensor(recon_world.astype(np.float32))).numpy()
    d_true, _ = cKDTree(recon_world).query(visible_true)
    return {"accuracy_mm": round(1000 * float(acc.mean()), 2), "completion_mm": round(1000 * float(d_true.mean()), 2),
            "chamfer_mm": round(500 * float(acc.mean() + d_true.mean()), 2),
            "completeness": round(float(np.mean(d_true <= threshold_m)), 4)}


def match_objects(recon: list[PlacedObject], truth: list[PlacedObject]) -> dict[int, int]:
    """recon obj_id -> true obj_id by nearest bounding-box centre in the world."""
    def centre(o):
        return transform_points(o.T_world_obj, o.model.center_m[None, :])[0]
    out = {}
    for r in recon:
        d = [np.linalg.norm(centre(r) - centre(t)) for t in truth]
        out[r.obj_id] = truth[int(np.argmin(d))].obj_id
    return out


def real_split_mask_ious(scene_dir: str | Path, object_id_images, frame_positions: list[int],
                         recon_to_true: dict[int, int], min_visib_fract: float = 0.1) -> list[float]:
    """IoU of each written visible mask with ``object_id_images[frame] == true id`` (instances with
    visib_fract >= ``min_visib_fract``)."""
    import cv2

    sdir = Path(scene_dir)
    gts = json.loads((sdir / "scene_gt.json").read_text())
    infos = json.loads((sdir / "scene_gt_info.json").read_text())
    ious = []
    for im, insts in gts.items():
        ids = np.asarray(object_id_images[frame_positions[int(im)]])
        for k, (g, info) in enumerate(zip(insts, infos[im])):
            if info["visib_fract"] < min_visib_fract:
                continue
            m = cv2.imread(str(sdir / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            t = ids == recon_to_true[g["obj_id"]]
            union = np.count_nonzero(m | t)
            ious.append(np.count_nonzero(m & t) / union if union else 1.0)
    return ious
