"""Reader of a BOP dataset folder (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md).

:class:`BopDataset` finds the files of a dataset root and reads them with the one BOP record module
(:mod:`presim.formats.bop`: one record type per JSON row, all in **metres**) and the one PLY reader
(:mod:`presim.formats.ply`). The record types and readers are re-exported here for convenience.

Layout of a BOP dataset root::

    camera.json                       (optional) fx, fy, cx, cy, width, height, depth_scale
    models/obj_XXXXXX.ply             models in mm, models/models_info.json
    models_eval/obj_XXXXXX.ply        (optional) uniformly resampled models used by bop_toolkit's metrics
    test_targets_bop19.json           (optional) the official evaluation targets
    <split>/XXXXXX/                   one folder per scene (split: test, train, val, train_pbr, ...)
        scene_camera.json             per image: cam_K (3x3 row-major), depth_scale, [cam_R_w2c, cam_t_w2c]
        scene_gt.json                 per image: [{cam_R_m2c (3x3 row-major), cam_t_m2c (mm), obj_id}, ...]
        scene_gt_info.json            per image: [{bbox_obj, bbox_visib, px_count_*, visib_fract}, ...]
        rgb/XXXXXX.png|jpg, depth/XXXXXX.png, mask/XXXXXX_YYYYYY.png, mask_visib/XXXXXX_YYYYYY.png

Conventions: ``cam_R_m2c, cam_t_m2c`` map model to camera (``x_cam = R x_model + t``), i.e. they
are ``T_cam_obj``; ``cam_R_w2c, cam_t_w2c`` are ``T_cam_world``. Depth PNGs hold
``depth_mm / depth_scale``, so ``depth_m = png * depth_scale / 1000``.

Example:
    >>> ds = BopDataset("/data/lmo")                              # doctest: +SKIP
    >>> for inst in ds.scene_gt(2)[3]: print(inst.obj_id, inst.T_cam_obj[:3, 3])   # doctest: +SKIP
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from presim.formats.bop import (
    M_TO_MM, MM_TO_M, BopCamera, GtInfo, GtInstance, ModelInfo, SceneCamera, Target, load_json,
    read_camera_json, read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info,
    read_test_targets,
)
from presim.formats.ply import PlyMesh, read_ply
from presim.geometry import Intrinsics
from presim.io_utils import read_image

__all__ = [
    "MM_TO_M",
    "M_TO_MM",
    "BopCamera",
    "SceneCamera",
    "GtInstance",
    "GtInfo",
    "ModelInfo",
    "Target",
    "load_json",
    "read_camera_json",
    "read_scene_camera",
    "read_scene_gt",
    "read_scene_gt_info",
    "read_models_info",
    "read_test_targets",
    "BopDataset",
]


# ---- dataset ----------------------------------------------------------------------------------

_SCENE_RE = re.compile(r"^\d{6}$")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif")


class BopDataset:
    """A BOP dataset root: scenes of a split, their cameras, GT, GT info, images and object models.

    JSON files are read lazily and cached. Ids are integers; files are ``{id:06d}``.

    Args:
        root: dataset folder (holds ``models/`` and the split folder).
        split: split folder name (``test``, ``train_pbr``, ``val``, ...). ``split_type`` is appended
            with an underscore when given (``test_primesense``).
    """

    def __init__(self, root: str | Path, split: str = "test", split_type: str | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: BOP dataset folder not found")
        self.split = split if not split_type else f"{split}_{split_type}"
        self._cache: dict = {}

    # -- paths
    @property
    def split_dir(self) -> Path:
        return self.root / self.split

    def scene_dir(self, scene_id: int) -> Path:
        return self.split_dir / f"{int(scene_id):06d}"

    @property
    def models_dir(self) -> Path:
        return self.root / "models"

    @property
    def models_eval_dir(self) -> Path:
        return self.root / "models_eval"

    def model_path(self, obj_id: int, eval: bool = False) -> Path:
        """``models_eval/obj_XXXXXX.ply`` when ``eval`` and it exists, else ``models/...``."""
        name = f"obj_{int(obj_id):06d}.ply"
        if eval and (self.models_eval_dir / name).is_file():
            return self.models_eval_dir / name
        p = self.models_dir / name
        if not p.is_file():
            raise FileNotFoundError(f"{p}: model of object {obj_id} not found")
        return p

    def image_path(self, scene_id: int, im_id: int, kind: str = "rgb") -> Path:
        """Path of ``rgb``/``gray``/``depth`` image ``im_id`` (png or jpg, whichever exists)."""
        d = self.scene_dir(scene_id) / kind
        for ext in _IMAGE_EXTS:
            p = d / f"{int(im_id):06d}{ext}"
            if p.is_file():
                return p
        raise FileNotFoundError(f"{d / f'{int(im_id):06d}.png'}: {kind} image not found")

    def mask_path(self, scene_id: int, im_id: int, gt_idx: int, visib: bool = True) -> Path:
        d = self.scene_dir(scene_id) / ("mask_visib" if visib else "mask")
        return d / f"{int(im_id):06d}_{int(gt_idx):06d}.png"

    # -- listings
    def scene_ids(self) -> list[int]:
        """Scene ids of the split (folders named with 6 digits)."""
        if not self.split_dir.is_dir():
            raise FileNotFoundError(f"{self.split_dir}: split folder not found")
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and _SCENE_RE.match(p.name))

    def image_ids(self, scene_id: int) -> list[int]:
        """Image ids of a scene, from scene_camera.json (else scene_gt.json)."""
        if (self.scene_dir(scene_id) / "scene_camera.json").is_file():
            return sorted(self.scene_camera(scene_id))
        return sorted(self.scene_gt(scene_id))

    def obj_ids(self) -> list[int]:
        return sorted(self.models_info())

    # -- JSON files (cached)
    def _cached(self, key, fn, *args):
        if key not in self._cache:
            self._cache[key] = fn(*args)
        return self._cache[key]

    def camera(self) -> BopCamera:
        """Dataset-level ``camera.json`` (``camera*.json`` when the plain name is absent)."""
        p = self.root / "camera.json"
        if not p.is_file():
            cands = sorted(self.root.glob("camera*.json"))
            if not cands:
                raise FileNotFoundError(f"{p}: file not found")
            p = cands[0]
        return self._cached(("camera",), read_camera_json, p)

    def scene_camera(self, scene_id: int) -> dict[int, SceneCamera]:
        return self._cached(("sc", scene_id), read_scene_camera, self.scene_dir(scene_id) / "scene_camera.json")

    def scene_gt(self, scene_id: int) -> dict[int, list[GtInstance]]:
        return self._cached(("gt", scene_id), read_scene_gt, self.scene_dir(scene_id) / "scene_gt.json")

    def scene_gt_info(self, scene_id: int) -> dict[int, list[GtInfo]]:
        return self._cached(("gti", scene_id), read_scene_gt_info, self.scene_dir(scene_id) / "scene_gt_info.json")

    def models_info(self, eval: bool = False) -> dict[int, ModelInfo]:
        """``models[_eval]/models_info.json`` (``eval`` falls back to ``models/``)."""
        p = self.models_eval_dir / "models_info.json"
        if not (eval and p.is_file()):
            p = self.models_dir / "models_info.json"
        return self._cached(("mi", str(p)), read_models_info, p)

    def test_targets(self, path: str | Path | None = None) -> list[Target]:
        """Targets from ``path`` or the root's ``test_targets_bop19.json``."""
        p = Path(path) if path is not None else self.root / "test_targets_bop19.json"
        return self._cached(("tt", str(p)), read_test_targets, p)

    # -- data
    def model_mesh_m(self, obj_id: int, eval: bool = False) -> PlyMesh:
        """The PLY of ``obj_id`` with positions in **metres**, float64 (``eval``: from models_eval/
        when present). The metrics use these points as the file has them; the object model with
        id, name and symmetries is :func:`presim.datasets.objects.load_model`."""
        p = self.model_path(obj_id, eval=eval)
        return self._cached(("model", str(p)), lambda q: read_ply(q).scaled(MM_TO_M), p)  # BOP mm -> m

    def intrinsics(self, scene_id: int, im_id: int) -> Intrinsics:
        """Per-image intrinsics (cam_K of scene_camera.json) with the image size of camera.json."""
        cams = self.scene_camera(scene_id)
        if im_id not in cams:
            raise ValueError(f"{self.scene_dir(scene_id) / 'scene_camera.json'}: no entry for image {im_id}")
        try:
            w, h = self.camera().K.width, self.camera().K.height
        except FileNotFoundError:
            import cv2
            for kind in ("rgb", "gray", "depth"):  # no camera.json: size from any image of the view
                try:
                    path = self.image_path(scene_id, im_id, kind)
                    break
                except FileNotFoundError:
                    continue
            else:
                raise FileNotFoundError(f"{self.root / 'camera.json'}: not found and image {im_id} of scene "
                                        f"{scene_id} has no rgb/gray/depth file to take the size from") from None
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"{path}: unreadable image") from None
            h, w = img.shape[:2]
        return cams[im_id].intrinsics(w, h)

    def read_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """uint8 (H, W, 3) RGB."""
        return read_image(self.image_path(scene_id, im_id, "rgb"), kind="color")

    def read_depth_m(self, scene_id: int, im_id: int) -> np.ndarray:
        """float32 (H, W) z-depth in metres, 0 = invalid (``png * depth_scale / 1000``)."""
        raw = read_image(self.image_path(scene_id, im_id, "depth"), kind="depth")
        scale = self.scene_camera(scene_id)[im_id].depth_scale
        return (raw.astype(np.float32) * np.float32(scale * MM_TO_M))  # BOP mm x depth_scale -> m

    def read_mask(self, scene_id: int, im_id: int, gt_idx: int, visib: bool = True) -> np.ndarray:
        """bool (H, W) mask of instance ``gt_idx``."""
        return read_image(self.mask_path(scene_id, im_id, gt_idx, visib), kind="mask") > 0
