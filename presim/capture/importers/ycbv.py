"""YCB-Video frames (PoseCNN release layout).

Files (in SRC or SRC/data)::

    NNNNNN-color.png     RGB 640x480
    NNNNNN-depth.png     uint16; depth_m = value / factor_depth (factor_depth = 10000 in the release)
    NNNNNN-meta.mat      MATLAB v5 (scipy.io.loadmat): intrinsic_matrix (3x3), factor_depth,
                         poses (3x4xK, [R|t] model -> camera, metres), cls_indexes (K, 1-based),
                         rotation_translation_matrix (3x4 world -> camera), optional
    models/<NNN_name>/points.xyz   model points (metres); class index i = i-th name in sorted order
                                   (models folder: SRC/models or SRC/../models)

Camera pose: ``T_world_cam = inv(rotation_translation_matrix)`` when present, else identity (each
frame its own world; noted). Objects: ``T_world_obj = T_world_cam @ T_cam_obj`` from the first frame
that shows the class; a class seen again with a pose more than 1 cm / 2 deg away is noted (frames
from different videos do not share a world).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, check_sizes, checked_pose, image_size_wh, require_file, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta, SceneObject
from presim.geometry import Intrinsics, compose, invert, rotation_angle_rad

NAME = "ycbv"
VERSION = "1"
_META_RE = re.compile(r"^(\d+)-meta\.mat$")


def _data_dir(src: Path) -> Path | None:
    for d in (src, src / "data"):
        if d.is_dir() and any(_META_RE.match(p.name) for p in d.iterdir()):
            return d
    return None


def detect(src: Path) -> bool:
    return src.is_dir() and _data_dir(src) is not None


def load_meta(path: Path) -> dict:
    import scipy.io

    require_file(path, "meta.mat")
    try:
        m = scipy.io.loadmat(str(path))
    except Exception as e:  # noqa: BLE001 - any MATLAB parse error = corrupt file
        raise SceneError(f"{path}: unreadable or corrupt .mat ({e})") from None
    for k in ("intrinsic_matrix", "factor_depth"):
        if k not in m:
            raise SceneError(f"{path}: missing '{k}'")
    return m


def _class_names(models_dir: Path | None) -> list[str]:
    if models_dir is None:
        return []
    return sorted(p.name for p in models_dir.iterdir() if p.is_dir())


def read(src: Path, every: int = 1, max_frames: int | None = None) -> Scene:
    src = Path(src)
    ddir = _data_dir(src)
    if ddir is None:
        raise SceneError(f"{src}: no NNNNNN-meta.mat files (in the folder or data/)")
    nums = sorted(m.group(1) for p in ddir.iterdir() if (m := _META_RE.match(p.name)))
    nums = [nums[i] for i in select_indices(len(nums), every, max_frames)]
    models_dir = next((d for d in (src / "models", src.parent / "models", ddir.parent / "models") if d.is_dir()), None)
    names = _class_names(models_dir)

    colors, depths, Ks, poses, factors = [], [], [], [], []
    objects: dict[int, SceneObject] = {}
    notes = []
    no_cam_pose = []
    for num in nums:
        mpath = ddir / f"{num}-meta.mat"
        m = load_meta(mpath)
        colors.append(require_file(ddir / f"{num}-color.png", "color image"))
        depths.append(require_file(ddir / f"{num}-depth.png", "depth image"))
        Ks.append(np.asarray(m["intrinsic_matrix"], dtype=np.float64).reshape(3, 3))
        f = float(np.asarray(m["factor_depth"]).ravel()[0])
        if not np.isfinite(f) or f <= 0:
            raise SceneError(f"{mpath}: factor_depth must be positive, got {f}")
        factors.append(f)
        if "rotation_translation_matrix" in m:
            Rt = np.asarray(m["rotation_translation_matrix"], dtype=np.float64)
            if Rt.shape != (3, 4):
                raise SceneError(f"{mpath}: rotation_translation_matrix must be 3x4, got {Rt.shape}")
            T_cam_world = checked_pose(np.vstack([Rt, [0, 0, 0, 1]]), f"{mpath} rotation_translation_matrix")
            T_world_cam = invert(T_cam_world)
        else:
            T_world_cam = np.eye(4)
            no_cam_pose.append(num)
        poses.append(T_world_cam)
        if "poses" in m and "cls_indexes" in m:
            P = np.asarray(m["poses"], dtype=np.float64)
            if P.ndim == 2:
                P = P[:, :, None]
            cls = np.asarray(m["cls_indexes"]).ravel().astype(int)
            if P.shape[:2] != (3, 4) or P.shape[2] != len(cls):
                raise SceneError(f"{mpath}: poses {P.shape} do not match {len(cls)} cls_indexes")
            for k, c in enumerate(cls):
                T_cam_obj = checked_pose(np.vstack([P[:, :, k], [0, 0, 0, 1]]), f"{mpath} poses[:, :, {k}]")
                T_world_obj = compose(T_world_cam, T_cam_obj)
                if c in objects:
                    prev = objects[c].T_world_obj
                    if (np.linalg.norm(prev[:3, 3] - T_world_obj[:3, 3]) > 0.01
                            or rotation_angle_rad(prev[:3, :3], T_world_obj[:3, :3]) > np.radians(2)):
                        notes.append(f"class {c} in frame {num} disagrees with its first pose (kept the first)")
                    continue
                if names and not 1 <= c <= len(names):
                    raise SceneError(f"{mpath}: class index {c} outside 1..{len(names)} ({models_dir})")
                name = names[c - 1] if names else f"class_{c:02d}"
                model = models_dir / name / "points.xyz" if names else None
                if model is not None and not model.is_file():
                    raise SceneError(f"{model}: model points of {name} not found")
                objects[c] = SceneObject(int(c), name, T_world_obj, str(model) if model else None)
    w, h = image_size_wh(colors[0])
    Ks = [Intrinsics.from_K(K, w, h) for K in Ks]
    check_sizes(colors, (w, h), "color")
    check_sizes(depths, (w, h), "depth")
    factor_by_path = {str(d): f for d, f in zip(depths, factors)}

    def decode(raw: np.ndarray, path: Path) -> np.ndarray:
        if not np.issubdtype(raw.dtype, np.integer):
            raise SceneError(f"{path}: YCB-Video depth must be an integer PNG, got {raw.dtype}")
        return raw.astype(np.float32) / np.float32(factor_by_path[str(path)])

    if no_cam_pose:
        notes.append(f"no rotation_translation_matrix in {len(no_cam_pose)} frames: identity camera pose")
    if models_dir is None:
        notes.append("no models/ folder: objects without models")
    notes.append("stamps = frame number / 30 s")
    source = FileFrameSource(colors, depths, Ks, decode)
    return Scene([f"{n}" for n in nums], np.array([int(n) for n in nums], dtype=np.float64) / 30.0,
                 np.stack(poses), Ks, source, SceneMeta(str(src.resolve()), NAME, VERSION, notes=tuple(notes)),
                 objects=[objects[c] for c in sorted(objects)])
