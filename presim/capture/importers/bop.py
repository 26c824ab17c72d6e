"""BOP scene folders (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md).

Files::

    SCENE/scene_camera.json   per im_id: cam_K (9, row-major), depth_scale, cam_R_w2c (9), cam_t_w2c (3, mm)
    SCENE/rgb/{im_id:06d}.png|jpg
    SCENE/depth/{im_id:06d}.png   uint16; depth_mm = value * depth_scale; 0 = invalid
    SCENE/scene_gt.json       optional, per im_id: [{obj_id, cam_R_m2c (9), cam_t_m2c (3, mm)}]
    DATASET/models/obj_{obj_id:06d}.ply   meshes in millimetres (models folder = SCENE/../../models)

Units: BOP is millimetres; everything becomes metres here (poses, depth, and the object meshes, which
are written scaled to metres into a temporary folder that ``save_scene`` copies into the scene).
Camera poses: ``T_world_cam = inv([cam_R_w2c | cam_t_w2c])``. Scenes without ``cam_R_w2c`` (LM, LM-O)
are static, so the camera poses follow from one object's ground truth: the world is the frame of the
first object annotated in every frame (``T_world_cam = inv(T_cam_obj)``), noted in the meta.
The JSON files are read into the BOP records of :mod:`presim.formats.bop` (already in metres) and the
models through :mod:`presim.formats.ply`; their errors come back as ``SceneError`` naming the file.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, check_sizes, checked_pose, image_size_wh, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta, SceneObject
from presim.formats.bop import MM_TO_M, GtInstance, SceneCamera, read_scene_camera, read_scene_gt
from presim.formats.ply import read_ply, write_ply
from presim.geometry import Intrinsics, compose, invert

NAME = "bop"
VERSION = "1"


def detect(src: Path) -> bool:
    return src.is_dir() and (src / "scene_camera.json").is_file()


def _read(reader, path: Path):
    """A :mod:`presim.formats.bop` reader's result, its errors as ``SceneError``."""
    try:
        return reader(path)
    except (OSError, ValueError) as e:
        raise SceneError(str(e)) from None


def _model_in_metres(src_ply: Path, out_dir: Path) -> Path:
    try:
        mesh = read_ply(src_ply)
    except (OSError, ValueError) as e:
        raise SceneError(f"{src_ply}: unreadable model ({e})") from None
    dst = out_dir / src_ply.name
    # BOP models are in millimetres; normals are left out (the scene recomputes them from faces).
    write_ply(dst, mesh.vertices * MM_TO_M, mesh.faces, colors=mesh.colors)
    return dst


def read(src: Path, every: int = 1, max_frames: int | None = None, models_dir: Path | None = None) -> Scene:
    src = Path(src)
    cam_path = src / "scene_camera.json"
    cams: dict[int, SceneCamera] = _read(read_scene_camera, cam_path)
    im_ids = sorted(cams)
    if not im_ids:
        raise SceneError(f"{cam_path}: no images")
    im_ids = [im_ids[i] for i in select_indices(len(im_ids), every, max_frames)]
    rgb_dir = src / "rgb"
    depth_dir = src / "depth"
    if not depth_dir.is_dir():
        raise SceneError(f"{depth_dir}: no depth folder (PreSim needs depth for every frame)")
    gt_path = src / "scene_gt.json"
    gt: dict[int, list[GtInstance]] = _read(read_scene_gt, gt_path) if gt_path.is_file() else {}

    colors, depths, Ks, scales = [], [], [], []
    for im in im_ids:
        c = rgb_dir / f"{im:06d}.png"
        if not c.is_file():
            c = rgb_dir / f"{im:06d}.jpg"
        if not c.is_file():
            raise SceneError(f"{rgb_dir / f'{im:06d}.png'}: color image not found (nor .jpg)")
        colors.append(c)
        depths.append(depth_dir / f"{im:06d}.png")
        Ks.append(cams[im].K)
        scales.append(cams[im].depth_scale)
    w, h = image_size_wh(colors[0])
    Ks = [Intrinsics.from_K(K, w, h) for K in Ks]
    check_sizes(colors, (w, h), "color")
    check_sizes(depths, (w, h), "depth")

    notes = []
    if all(cams[im].T_cam_world is not None for im in im_ids):
        poses = [invert(checked_pose(cams[im].T_cam_world, f"{cam_path} image {im} cam_R_w2c/cam_t_w2c"))
                 for im in im_ids]
    else:
        anchor = _anchor_object(gt, im_ids, cam_path, gt_path)
        poses = []
        for im in im_ids:
            a = next(a for a in gt[im] if a.obj_id == anchor)
            poses.append(invert(checked_pose(a.T_cam_obj, f"{gt_path} image {im} obj {anchor}")))
        notes.append(f"no cam_R_w2c: world = frame of object {anchor} (static scene), poses from scene_gt")

    objects = []
    if gt:
        if models_dir is None:
            cand = src.parent.parent / "models"
            models_dir = cand if cand.is_dir() else None
        out_dir = None
        if models_dir is not None:
            # Models converted to metres live here until the scene is saved (save_scene copies them);
            # removed when the process exits.
            out_dir = Path(tempfile.mkdtemp(prefix="presim-bop-models-"))
            atexit.register(shutil.rmtree, out_dir, ignore_errors=True)
        seen: set[int] = set()
        for k, im in enumerate(im_ids):
            anns = gt.get(im, [])
            new = sorted({a.obj_id for a in anns} - seen)
            for a in anns:
                oid = a.obj_id
                if oid not in new:
                    continue
                T_cam_obj = checked_pose(a.T_cam_obj, f"{gt_path} image {im} obj {oid}")
                model = None
                if models_dir is not None:
                    ply = Path(models_dir) / f"obj_{oid:06d}.ply"
                    if not ply.is_file():
                        raise SceneError(f"{ply}: model of object {oid} not found")
                    model = str(_model_in_metres(ply, out_dir))
                objects.append(SceneObject(oid, f"obj_{oid:06d}", compose(poses[k], T_cam_obj), model))
            seen.update(new)
        if models_dir is None:
            notes.append("objects without models (no models folder at ../../models)")

    scale_by_path = {str(d): s for d, s in zip(depths, scales)}

    def decode(raw: np.ndarray, path: Path) -> np.ndarray:
        if not np.issubdtype(raw.dtype, np.integer):
            raise SceneError(f"{path}: BOP depth must be an integer PNG, got {raw.dtype}")
        # depth_mm = value * depth_scale
        return raw.astype(np.float32) * np.float32(scale_by_path[str(path)] * MM_TO_M)

    source = FileFrameSource(colors, depths, Ks, decode)
    ids = [f"{im:06d}" for im in im_ids]
    notes.append("no timestamps in BOP: stamp = im_id / 30 s")
    return Scene(ids, np.array(im_ids, dtype=np.float64) / 30.0, np.stack(poses), Ks, source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=tuple(notes)), objects=objects)


def _anchor_object(gt: dict[int, list[GtInstance]], im_ids: list[int], cam_path: Path, gt_path: Path) -> int:
    if not gt:
        raise SceneError(f"{cam_path}: no cam_R_w2c/cam_t_w2c and no scene_gt.json: camera poses unknown")
    common = None
    for im in im_ids:
        anns = gt.get(im)
        if not anns:
            raise SceneError(f"{gt_path}: image {im} has no annotation and {cam_path.name} no cam_R_w2c")
        ids = [a.obj_id for a in anns]
        single = {o for o in ids if ids.count(o) == 1}
        common = single if common is None else common & single
    if not common:
        raise SceneError(f"{cam_path}: no cam_R_w2c and no single-instance object annotated in every image")
    return min(common)
