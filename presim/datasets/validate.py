"""Schema and consistency validation of a BOP dataset written by ``presim gen-bop``.

Checks, each problem reported with the file it is in:

- ``camera.json`` has fx, fy, cx, cy, width, height, depth_scale; every ``cam_K`` agrees with it.
- ``models/models_info.json`` has an entry (diameter > 0, min_*, size_*) for every
  ``models/obj_XXXXXX.ply``; each PLY loads and its extents match the entry (0.01 mm).
- every scene folder is finished (``.presim_complete``) and has scene_camera / scene_gt /
  scene_gt_info with the same image ids and instance counts; rotations are orthonormal; obj_ids
  have models.
- every image has rgb/ and depth/ (16-bit) files of the camera's size; every instance has mask/
  and mask_visib/ files; mask_visib lies inside mask; px_count_visib, bbox_visib and visib_fract
  agree with the mask files; 0 <= px_count_visib <= px_count_all.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from presim.datasets import bop_reader as br
from presim.datasets.annotate import bbox_from_mask
from presim.formats.ply import read_ply
from presim.datasets.generate import COMPLETE_MARKER
from presim.io_utils import read_image

__all__ = ["validate_bop"]

_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
_INFO_KEYS = ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z")
_GT_INFO_KEYS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


def validate_bop(root: str | Path, splits: tuple[str, ...] | None = None, check_images: bool = True,
                 max_problems: int = 50) -> list[str]:
    """Validate the dataset at ``root``; returns the problems found (empty = valid).

    ``splits``: split folders to check (default: every folder holding 6-digit scene folders).
    ``check_images``: also open every image and mask (slower, the full check).
    """
    root = Path(root)
    problems: list[str] = []

    def bad(msg: str) -> None:
        if len(problems) < max_problems:
            problems.append(msg)

    if not root.is_dir():
        return [f"{root}: dataset folder not found"]
    cam_path = root / "camera.json"
    cam = None
    try:
        raw = br.load_json(cam_path)
        missing = [k for k in _CAMERA_KEYS if k not in raw]
        if missing:
            bad(f"{cam_path}: missing {missing}")
        cam = br.read_camera_json(cam_path)
    except (OSError, ValueError) as e:
        bad(f"{cam_path}: {e}")

    info_path = root / "models" / "models_info.json"
    infos: dict = {}
    try:
        raw_info = br.load_json(info_path)
        for k, e in raw_info.items():
            miss = [f for f in _INFO_KEYS if f not in e]
            if miss:
                bad(f"{info_path}: object {k} misses {miss}")
        infos = br.read_models_info(info_path)
    except (OSError, ValueError) as e:
        bad(f"{info_path}: {e}")
    for ply in sorted((root / "models").glob("obj_*.ply")):
        obj_id = int(ply.stem.split("_")[1])
        if obj_id not in infos:
            bad(f"{info_path}: no entry for {ply.name}")
            continue
        try:
            m = read_ply(ply)
        except (OSError, ValueError) as e:
            bad(f"{ply}: {e}")
            continue
        lo_mm = m.vertices.min(0)
        size_mm = m.vertices.max(0) - lo_mm
        inf = infos[obj_id]
        if np.abs(lo_mm - inf.min_m * br.M_TO_MM).max() > 0.01 or np.abs(size_mm - inf.size_m * br.M_TO_MM).max() > 0.01:
            bad(f"{ply}: extents {lo_mm}, {size_mm} mm disagree with models_info.json")

    if splits is None:
        splits = tuple(sorted(p.name for p in root.iterdir() if p.is_dir() and p.name != "models"
                              and any(c.is_dir() and c.name.isdigit() and len(c.name) == 6 for c in p.iterdir())))
    if not splits:
        bad(f"{root}: no split folder with scenes")
    for split in splits:
        ds = br.BopDataset(root, split=split)
        try:
            scene_ids = ds.scene_ids()
        except FileNotFoundError as e:
            bad(str(e))
            continue
        for sid in scene_ids:
            _validate_scene(ds, sid, cam, infos, check_images, bad)
    return problems


def _validate_scene(ds: br.BopDataset, sid: int, cam, infos: dict, check_images: bool, bad) -> None:
    sdir = ds.scene_dir(sid)
    if not (sdir / COMPLETE_MARKER).is_file():
        bad(f"{sdir}: scene is not finished (no {COMPLETE_MARKER}); rerun gen-bop to complete it")
        return
    try:
        cams, gts, gtis = ds.scene_camera(sid), ds.scene_gt(sid), ds.scene_gt_info(sid)
    except (OSError, ValueError) as e:
        bad(str(e))
        return
    raw_info = br.load_json(sdir / "scene_gt_info.json")
    if not (set(cams) == set(gts) == set(gtis)):
        bad(f"{sdir}: scene_camera / scene_gt / scene_gt_info have different image ids")
    for im_id in sorted(set(gts) & set(gtis) & set(cams)):
        where = f"{sdir} image {im_id}"
        if cam is not None and not np.allclose(cams[im_id].K, cam.K.K, atol=1e-6):
            bad(f"{where}: cam_K differs from camera.json")
        if len(gts[im_id]) != len(gtis[im_id]):
            bad(f"{where}: {len(gts[im_id])} scene_gt instances but {len(gtis[im_id])} scene_gt_info entries")
            continue
        for k, e in enumerate(raw_info[str(im_id)]):
            miss = [f for f in _GT_INFO_KEYS if f not in e]
            if miss:
                bad(f"{where} instance {k}: scene_gt_info misses {miss}")
        for k, (g, inf) in enumerate(zip(gts[im_id], gtis[im_id])):
            if infos and g.obj_id not in infos:
                bad(f"{where} instance {k}: obj_id {g.obj_id} has no model")
            if not 0 <= inf.px_count_visib <= inf.px_count_all:
                bad(f"{where} instance {k}: px_count_visib {inf.px_count_visib} not in [0, px_count_all]")
            vf = inf.px_count_visib / inf.px_count_all if inf.px_count_all else 0.0
            if abs(vf - inf.visib_fract) > 1e-6:
                bad(f"{where} instance {k}: visib_fract {inf.visib_fract} != px_count_visib / px_count_all")
        if not check_images:
            continue
        try:
            rgb = ds.read_rgb(sid, im_id)
            depth = read_image(ds.image_path(sid, im_id, "depth"), kind="depth")
        except (OSError, ValueError) as e:
            bad(str(e))
            continue
        if cam is not None and rgb.shape[:2] != (cam.K.height, cam.K.width):
            bad(f"{where}: rgb is {rgb.shape[1]}x{rgb.shape[0]}, camera.json says {cam.K.width}x{cam.K.height}")
        if depth.dtype != np.uint16 or depth.shape != rgb.shape[:2]:
            bad(f"{where}: depth must be uint16 {rgb.shape[:2]}, got {depth.dtype} {depth.shape}")
        for k, inf in enumerate(gtis[im_id]):
            try:
                m = ds.read_mask(sid, im_id, k, visib=False)
                mv = ds.read_mask(sid, im_id, k, visib=True)
            except (OSError, ValueError) as e:
                bad(str(e))
                continue
            if m.shape != rgb.shape[:2] or mv.shape != rgb.shape[:2]:
                bad(f"{where} instance {k}: mask size differs from the image")
                continue
            if np.any(mv & ~m):
                bad(f"{where} instance {k}: mask_visib is not inside mask")
            if int(mv.sum()) != inf.px_count_visib:
                bad(f"{where} instance {k}: px_count_visib {inf.px_count_visib} != mask_visib pixels {int(mv.sum())}")
            if tuple(bbox_from_mask(mv)) != tuple(inf.bbox_visib):
                bad(f"{where} instance {k}: bbox_visib {inf.bbox_visib} != box of mask_visib {bbox_from_mask(mv)}")
