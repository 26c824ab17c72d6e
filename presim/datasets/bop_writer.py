"""Writer of the BOP dataset format (files in millimetres, converted here from metres).

Layout written (bop_toolkit's ``docs/bop_datasets_format.md``)::

    OUT/camera.json                          fx fy cx cy width height depth_scale
    OUT/models/obj_XXXXXX.ply                models in mm (binary PLY), models/models_info.json
    OUT/<split>/XXXXXX/                      one scene (split ``train`` by default)
        rgb/IIIIII.png|jpg                   8-bit RGB
        depth/IIIIII.png                     uint16, depth_mm = value * depth_scale (0 = invalid)
        mask/IIIIII_NNNNNN.png               full silhouette of instance NNNNNN (0/255)
        mask_visib/IIIIII_NNNNNN.png         visible part
        scene_camera.json                    cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)
        scene_gt.json                        cam_R_m2c (row-major), cam_t_m2c (mm), obj_id
        scene_gt_info.json                   bbox_obj, bbox_visib, px_count_*, visib_fract
        scene_gt_coco.json                   (optional) COCO instances for 2D detectors

Per-frame files are produced as bytes (:func:`encode_frame`) so that a worker on another machine
can make them and the single writer process stores them atomically. Scene JSON files are written
by :func:`write_scene_json` at the end of a job (a scene folder without them is not finished).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np

from presim.datasets.annotate import InstanceAnnotation
from presim.datasets.objects import ObjectModel, models_info, write_model_ply_mm
from presim.formats.bop import BopCamera, SceneCamera
from presim.formats.depth_png import encode_depth_png
from presim.geometry import Intrinsics, invert
from presim.io_utils import atomic_write_bytes, atomic_write_json, atomic_write_text

__all__ = ["encode_frame", "scene_camera_entry", "camera_json", "write_models",
           "write_scene_json", "write_frame_files", "coco_rle", "coco_scene", "scene_dir",
           "json_dumps_stable", "bop_json_text", "DEFAULT_DEPTH_SCALE"]

DEFAULT_DEPTH_SCALE = 0.1
"""depth_mm = png value * depth_scale: 0.1 mm steps, up to 6.55 m (BOP's PBR datasets use 0.1)."""


def scene_dir(out: Path, split: str, scene_id: int) -> Path:
    return Path(out) / split / f"{int(scene_id):06d}"


def camera_json(K: Intrinsics, depth_scale: float) -> dict:
    """Dataset-level ``camera.json`` (:meth:`BopCamera.to_json`)."""
    return BopCamera(K=K, depth_scale=float(depth_scale)).to_json()


def scene_camera_entry(K: Intrinsics, T_world_cam: np.ndarray, depth_scale: float) -> dict:
    """``scene_camera.json`` entry (:meth:`SceneCamera.to_json`): cam_K (row-major), world-to-camera
    pose in mm, depth_scale."""
    T_cam_world = invert(np.asarray(T_world_cam, dtype=np.float64))
    return SceneCamera(K=K.K, depth_scale=float(depth_scale), T_cam_world=T_cam_world).to_json()


def _encode_png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()


def encode_frame(im_id: int, color: np.ndarray, depth_m: np.ndarray, annotations: Sequence[InstanceAnnotation],
                 depth_scale: float = DEFAULT_DEPTH_SCALE, image_format: str = "png",
                 jpg_quality: int = 95) -> tuple[dict[str, bytes], int]:
    """Encode one frame's image files. Returns ``({relative path in the scene folder: bytes},
    n_depth_clipped)``. ``depth_m`` is written as given (0 = invalid)."""
    if color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] != 3:
        raise ValueError(f"frame {im_id}: color must be uint8 (H,W,3), got {color.dtype} {color.shape}")
    if depth_m.shape != color.shape[:2]:
        raise ValueError(f"frame {im_id}: depth shape {depth_m.shape} != color {color.shape[:2]}")
    bgr = cv2.cvtColor(color, cv2.COLOR_RGB2BGR)
    files: dict[str, bytes] = {}
    if image_format == "png":
        files[f"rgb/{im_id:06d}.png"] = _encode_png(bgr)
    elif image_format == "jpg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)])
        if not ok:
            raise OSError(f"frame {im_id}: JPEG encoding failed")
        files[f"rgb/{im_id:06d}.jpg"] = buf.tobytes()
    else:
        raise ValueError(f"image format must be 'png' or 'jpg', got {image_format!r}")
    files[f"depth/{im_id:06d}.png"], n_clip = encode_depth_png(depth_m, depth_scale)
    for k, a in enumerate(annotations):
        files[f"mask/{im_id:06d}_{k:06d}.png"] = _encode_png(a.mask.astype(np.uint8) * 255)
        files[f"mask_visib/{im_id:06d}_{k:06d}.png"] = _encode_png(a.mask_visib.astype(np.uint8) * 255)
    return files, n_clip


def write_models(out: Path, models: Sequence[ObjectModel]) -> None:
    """``models/obj_XXXXXX.ply`` (mm) and ``models/models_info.json``."""
    ids = [m.obj_id for m in models]
    if len(set(ids)) != len(ids):
        raise ValueError(f"object ids must be unique, got {ids}")
    mdir = Path(out) / "models"
    for m in models:
        write_model_ply_mm(m, mdir / f"obj_{m.obj_id:06d}.ply")
    atomic_write_json(mdir / "models_info.json", models_info(models))


def coco_rle(mask: np.ndarray) -> dict:
    """Uncompressed COCO RLE of a boolean mask (column-major runs starting with background), as
    pycocotools' ``frPyObjects`` reads it."""
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    runs = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        runs = [0] + runs
    return {"counts": [int(r) for r in runs], "size": [int(mask.shape[0]), int(mask.shape[1])]}


def coco_scene(records: Sequence[dict], masks_visib: Mapping[tuple[int, int], dict], models: Sequence[ObjectModel],
               width: int, height: int, rgb_ext: str, min_visib_fract: float) -> dict:
    """COCO ``instances`` dict of one scene (bop_toolkit ``calc_gt_coco`` style: box and RLE of the
    visible mask, ``ignore`` when less than ``min_visib_fract`` is visible)."""
    images, anns = [], []
    for rec in records:
        im_id = rec["im_id"]
        images.append({"id": im_id, "file_name": f"rgb/{im_id:06d}{rgb_ext}", "width": width, "height": height})
        for k, (gt, info) in enumerate(zip(rec["scene_gt"], rec["scene_gt_info"])):
            if info["px_count_visib"] == 0:
                continue
            anns.append({"id": len(anns) + 1, "image_id": im_id, "category_id": gt["obj_id"],
                         "bbox": info["bbox_visib"], "area": info["px_count_visib"], "iscrowd": 0,
                         "ignore": bool(info["visib_fract"] < min_visib_fract),
                         "segmentation": masks_visib[(im_id, k)]})
    cats = [{"id": m.obj_id, "name": m.name, "supercategory": "object"} for m in sorted(models, key=lambda m: m.obj_id)]
    return {"info": {"description": "PreSim BOP dataset", "version": "1.0"}, "licenses": [],
            "images": images, "annotations": anns, "categories": cats}


def bop_json_text(d: Mapping[str, object]) -> str:
    """JSON in bop_toolkit's layout: one key per line, each value on one line (compact, diffable)."""
    lines = [f"  {json.dumps(str(k))}: {json.dumps(v)}" for k, v in d.items()]
    return "{\n" + ",\n".join(lines) + "\n}\n"


def write_scene_json(sdir: Path, records: Sequence[dict], coco: dict | None = None) -> None:
    """Write scene_camera / scene_gt / scene_gt_info (and COCO) JSON from per-frame records, each
    atomically; scene_gt_info.json last (it marks the scene's annotations complete)."""
    sdir = Path(sdir)
    cams = {str(r["im_id"]): r["scene_camera"] for r in records}
    gts = {str(r["im_id"]): r["scene_gt"] for r in records}
    infos = {str(r["im_id"]): r["scene_gt_info"] for r in records}
    atomic_write_text(sdir / "scene_camera.json", bop_json_text(cams))
    atomic_write_text(sdir / "scene_gt.json", bop_json_text(gts))
    if coco is not None:
        atomic_write_json(sdir / "scene_gt_coco.json", coco, indent=None)
    atomic_write_text(sdir / "scene_gt_info.json", bop_json_text(infos))


def write_frame_files(sdir: Path, files: Mapping[str, bytes]) -> None:
    """Store one frame's encoded files, each atomically."""
    for rel, data in files.items():
        atomic_write_bytes(Path(sdir) / rel, data)


def json_dumps_stable(obj) -> str:
    """Deterministic JSON text (used for job fingerprints)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))
