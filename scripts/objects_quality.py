"""Reconstructed objects vs the sample scene's true meshes (docs/objects.md, "Quality").

    python scripts/objects_quality.py SAMPLE_SCENE_COPY BOP_OUT

SAMPLE_SCENE_COPY: a sample scene on which `presim objects` and `presim gen-bop-real --out BOP_OUT`
ran (its true objects are kept in scene.json under `objects_replaced`). Prints JSON.
"""

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from presim.capture.sample_scene import load_sample_ground_truth
from presim.capture.scene import SceneObject
from presim.capture.store import load_scene
from presim.datasets.object_sources import objects_from_scene
from presim.datasets.recon_quality import (
    match_objects, real_split_mask_ious, sample_surface, surface_metrics, visible_samples,
)
from presim.geometry import transform_points


def main(scene_dir: str, bop_out: str) -> dict:
    scene = load_scene(scene_dir)
    gt = load_sample_ground_truth(scene_dir)
    hdr = json.loads((Path(scene_dir) / "scene.json").read_text())
    true_objs = [SceneObject(o["obj_id"], o["name"], np.asarray(o["T_world_obj"]), o["model_path"])
                 for o in hdr["objects_replaced"]]
    truth = objects_from_scene(replace(scene, objects=true_objs))
    recon = objects_from_scene(scene)
    m = match_objects(recon, truth)
    rows = []
    for r in recon:
        t = next(o for o in truth if o.obj_id == m[r.obj_id])
        tv = transform_points(t.T_world_obj, t.model.vertices_m)
        samples = sample_surface(tv, t.model.faces, 20000)
        views = visible_samples(samples, scene.T_world_cam, scene.intrinsics, gt.depth_clean_m)
        import open3d as o3d

        pts_file = Path(scene_dir) / next(o for o in hdr["objects"] if o["obj_id"] == r.obj_id)["points_path"]
        rp = np.asarray(o3d.io.read_point_cloud(str(pts_file)).points)  # the cloud, also when a mesh is the model
        rw = transform_points(r.T_world_obj, rp)
        row = {"obj_id": r.obj_id, "true": t.model.name, "visible_frac_of_surface": round(float(np.mean(views > 0)), 3)}
        row.update(surface_metrics(rw, tv, t.model.faces, samples[views > 0]))
        row["completeness_seen_gt5"] = surface_metrics(rw, tv, t.model.faces, samples[views > 5])["completeness"]
        rows.append(row)
    sdir = Path(bop_out) / "real" / "000000"
    ious = real_split_mask_ious(sdir, gt.object_id, list(range(len(scene))), m)
    out = {"objects_found": len(recon), "true_objects": len(truth), "matched_true": sorted(set(m.values())),
           "per_object": rows,
           "mean_chamfer_mm": round(float(np.mean([r["chamfer_mm"] for r in rows])), 2),
           "mean_completeness": round(float(np.mean([r["completeness"] for r in rows])), 4),
           "mask_iou_mean": round(float(np.mean(ious)), 4), "mask_iou_median": round(float(np.median(ious)), 4),
           "mask_iou_min": round(float(np.min(ious)), 4), "instances": len(ious)}
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2]), indent=1))
