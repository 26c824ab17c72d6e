"""BOP records: one frozen type per row of each BOP JSON file, with its reader and its JSON entry.

Format reference: bop_toolkit's ``docs/bop_datasets_format.md``. BOP files are millimetres; every
record holds **metres** (converted here, at the border, with :data:`MM_TO_M` / :data:`M_TO_MM`).

======================  ====================  =======================================
file                    record                reader
======================  ====================  =======================================
camera.json             :class:`BopCamera`    :func:`read_camera_json`
scene_camera.json       :class:`SceneCamera`  :func:`read_scene_camera`
scene_gt.json           :class:`GtInstance`   :func:`read_scene_gt`
scene_gt_info.json      :class:`GtInfo`       :func:`read_scene_gt_info`
models/models_info.json :class:`ModelInfo`    :func:`read_models_info`
test_targets_bop19.json :class:`Target`       :func:`read_test_targets`
======================  ====================  =======================================

Each record's ``to_json()`` gives the entry as BOP writes it (the dataset writer uses them), so a
record read back from a written file equals the record written (tested). Readers raise
``FileNotFoundError`` / ``ValueError`` whose message starts with the file and names the entry.

Conventions: ``cam_R_m2c, cam_t_m2c`` map model to camera (``x_cam = R x_model + t``), i.e. they
are ``T_cam_obj``; ``cam_R_w2c, cam_t_w2c`` are ``T_cam_world``; rotations are row-major.

Example:
    >>> gt = read_scene_gt("lmo/test/000002/scene_gt.json")      # doctest: +SKIP
    >>> gt[3][0].T_cam_obj[:3, 3]                                 # metres  # doctest: +SKIP
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.geometry import Intrinsics, make_pose

__all__ = [
    "MM_TO_M", "M_TO_MM", "load_json",
    "BopCamera", "SceneCamera", "GtInstance", "GtInfo", "ModelInfo", "Target",
    "read_camera_json", "read_scene_camera", "read_scene_gt", "read_scene_gt_info",
    "read_models_info", "read_test_targets",
]

MM_TO_M = 1e-3
"""BOP lengths are millimetres; multiply by this to get metres."""
M_TO_MM = 1000.0
"""Metres to BOP millimetres (a multiplication, so written values are ``x * 1000.0`` exactly)."""

# Rotations in BOP files are stored with ~8 decimals; anything further off than this is not a rotation.
_ROT_TOL = 1e-2


# ---- small helpers ----------------------------------------------------------------------------

def load_json(path: str | Path):
    """Parsed JSON of ``path``; ``FileNotFoundError`` / ``ValueError`` naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with open(path, "r", encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None


def _int_key(path: Path, key) -> int:
    try:
        return int(key)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: key {key!r} is not an integer id") from None


def _keyed(path: Path, kind: str, lists: bool = False):
    """``(id, entry)`` of a BOP file keyed by ``kind`` id (``lists``: each entry a list of rows)."""
    d = load_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected an object keyed by {kind} id")
    for key, e in d.items():
        id_ = _int_key(path, key)
        if lists and not isinstance(e, list):
            raise ValueError(f"{path}: {kind} {id_}: expected a list of instances")
        yield id_, e


def _floats(path: Path, where: str, value, n: int) -> np.ndarray:
    """``value`` as a float64 array of exactly ``n`` finite numbers, else a clear error."""
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {where}: expected {n} numbers, got {value!r}") from None
    if a.size != n:
        raise ValueError(f"{path}: {where}: expected {n} numbers, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{path}: {where}: contains non-finite values")
    return a


def _rotation(path: Path, where: str, value) -> np.ndarray:
    R = _floats(path, where, value, 9).reshape(3, 3)  # row-major, as BOP writes it
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > _ROT_TOL or np.linalg.det(R) < 0:
        raise ValueError(f"{path}: {where}: not a rotation (max |R R^T - I| = {err:.3g}, "
                         f"det = {np.linalg.det(R):.3g})")
    return R


def _require(path: Path, where: str, d: dict, key: str):
    if not isinstance(d, dict):
        raise ValueError(f"{path}: {where}: expected an object, got {type(d).__name__}")
    if key not in d:
        raise ValueError(f"{path}: {where}: missing field '{key}'")
    return d[key]


# ---- camera -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class BopCamera:
    """Dataset-level camera from ``camera.json``."""

    K: Intrinsics
    """Intrinsics (pixels) and image size."""
    depth_scale: float
    """Depth PNG value x depth_scale = depth in mm."""

    def to_json(self) -> dict:
        """``camera.json`` content (keys sorted, as bop_toolkit writes it)."""
        K = self.K
        return {"cx": K.cx, "cy": K.cy, "depth_scale": float(self.depth_scale), "fx": K.fx, "fy": K.fy,
                "height": K.height, "width": K.width}


def read_camera_json(path: str | Path) -> BopCamera:
    """Read a BOP ``camera.json`` (fx, fy, cx, cy, width, height, depth_scale)."""
    path = Path(path)
    d = load_json(path)
    vals = [_require(path, "camera", d, k) for k in ("fx", "fy", "cx", "cy", "width", "height")]
    try:
        K = Intrinsics(*(float(v) for v in vals[:4]), int(vals[4]), int(vals[5]))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: bad camera parameters ({e})") from None
    return BopCamera(K=K, depth_scale=float(d.get("depth_scale", 1.0)))


@dataclass(frozen=True)
class SceneCamera:
    """One image's entry of ``scene_camera.json``."""

    K: np.ndarray
    """(3, 3) float64 camera matrix (pixels)."""
    depth_scale: float
    """Depth PNG value x depth_scale = depth in mm (1.0 when absent)."""
    T_cam_world: np.ndarray | None = None
    """(4, 4) world-to-camera pose in metres from cam_R_w2c / cam_t_w2c, or None when absent."""

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        return Intrinsics.from_K(self.K, width, height)

    def to_json(self) -> dict:
        """``scene_camera.json`` entry: cam_K (row-major), [cam_R_w2c, cam_t_w2c (mm)], depth_scale."""
        out: dict = {"cam_K": [float(x) for x in np.asarray(self.K, dtype=np.float64).ravel()]}
        if self.T_cam_world is not None:
            T = np.asarray(self.T_cam_world, dtype=np.float64)
            out["cam_R_w2c"] = [float(x) for x in T[:3, :3].ravel()]
            out["cam_t_w2c"] = [float(x) * M_TO_MM for x in T[:3, 3]]  # BOP border: m -> mm
        out["depth_scale"] = float(self.depth_scale)
        return out


def read_scene_camera(path: str | Path) -> dict[int, SceneCamera]:
    """Read ``scene_camera.json`` -> ``{im_id: SceneCamera}`` (translations converted to metres)."""
    path = Path(path)
    out: dict[int, SceneCamera] = {}
    for im_id, e in _keyed(path, "image"):
        where = f"image {im_id}"
        K = _floats(path, f"{where} cam_K", _require(path, where, e, "cam_K"), 9).reshape(3, 3)
        T = None
        if "cam_R_w2c" in e or "cam_t_w2c" in e:
            R = _rotation(path, f"{where} cam_R_w2c", _require(path, where, e, "cam_R_w2c"))
            t_mm = _floats(path, f"{where} cam_t_w2c", _require(path, where, e, "cam_t_w2c"), 3)
            T = make_pose(R, t_mm * MM_TO_M)  # BOP mm -> metres
        out[im_id] = SceneCamera(K=K, depth_scale=float(e.get("depth_scale", 1.0)), T_cam_world=T)
    return out


# ---- ground truth -----------------------------------------------------------------------------

@dataclass(frozen=True)
class GtInstance:
    """One annotated object instance of ``scene_gt.json``."""

    obj_id: int
    """Object id (models/obj_{obj_id:06d}.ply)."""
    R_m2c: np.ndarray
    """(3, 3) rotation model -> camera."""
    t_m2c_m: np.ndarray
    """(3,) translation model -> camera, metres."""

    @property
    def T_cam_obj(self) -> np.ndarray:
        """(4, 4) pose of the object in the camera frame (metres)."""
        return make_pose(self.R_m2c, self.t_m2c_m)

    @classmethod
    def from_pose(cls, obj_id: int, T_cam_obj: np.ndarray) -> "GtInstance":
        """Record of object ``obj_id`` at the 4x4 pose ``T_cam_obj`` (metres; stored as given)."""
        T = np.asarray(T_cam_obj, dtype=np.float64)
        return cls(obj_id=int(obj_id), R_m2c=T[:3, :3].copy(), t_m2c_m=T[:3, 3].copy())

    def to_json(self) -> dict:
        """``scene_gt.json`` entry: rotation row-major, translation in millimetres."""
        return {"cam_R_m2c": [float(x) for x in np.asarray(self.R_m2c, dtype=np.float64).ravel()],
                "cam_t_m2c": [float(x) * M_TO_MM for x in np.asarray(self.t_m2c_m, dtype=np.float64)],  # m -> mm
                "obj_id": int(self.obj_id)}


def read_scene_gt(path: str | Path) -> dict[int, list[GtInstance]]:
    """Read ``scene_gt.json`` -> ``{im_id: [GtInstance, ...]}`` in file order (the gt index)."""
    path = Path(path)
    out: dict[int, list[GtInstance]] = {}
    for im_id, insts in _keyed(path, "image", lists=True):
        lst = []
        for gt_idx, e in enumerate(insts):
            where = f"image {im_id} instance {gt_idx}"
            R = _rotation(path, f"{where} cam_R_m2c", _require(path, where, e, "cam_R_m2c"))
            t_mm = _floats(path, f"{where} cam_t_m2c", _require(path, where, e, "cam_t_m2c"), 3)
            obj_id = _require(path, where, e, "obj_id")
            if not isinstance(obj_id, int) or isinstance(obj_id, bool):
                raise ValueError(f"{path}: {where}: obj_id must be an integer, got {obj_id!r}")
            lst.append(GtInstance(obj_id=obj_id, R_m2c=R, t_m2c_m=t_mm * MM_TO_M))  # mm -> m
        out[im_id] = lst
    return out


@dataclass(frozen=True)
class GtInfo:
    """One instance's entry of ``scene_gt_info.json`` (same order as scene_gt)."""

    bbox_obj: tuple[int, int, int, int]
    """(x, y, w, h) box of the full projected object, pixels; (-1, -1, -1, -1) when not in view."""
    bbox_visib: tuple[int, int, int, int]
    """(x, y, w, h) box of the visible mask."""
    px_count_all: int
    """Pixels of the object silhouette (ignoring occlusion)."""
    px_count_valid: int
    """Silhouette pixels with valid depth."""
    px_count_visib: int
    """Visible pixels."""
    visib_fract: float
    """px_count_visib / px_count_all (0 when px_count_all is 0)."""

    def to_json(self) -> dict:
        """``scene_gt_info.json`` entry (same keys as bop_toolkit)."""
        return {"bbox_obj": [int(x) for x in self.bbox_obj], "bbox_visib": [int(x) for x in self.bbox_visib],
                "px_count_all": int(self.px_count_all), "px_count_valid": int(self.px_count_valid),
                "px_count_visib": int(self.px_count_visib), "visib_fract": float(self.visib_fract)}


def read_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    """Read ``scene_gt_info.json`` -> ``{im_id: [GtInfo, ...]}``."""
    path = Path(path)
    out: dict[int, list[GtInfo]] = {}
    for im_id, insts in _keyed(path, "image", lists=True):
        lst = []
        for gt_idx, e in enumerate(insts):
            where = f"image {im_id} instance {gt_idx}"
            try:
                lst.append(GtInfo(
                    bbox_obj=tuple(int(v) for v in _floats(path, f"{where} bbox_obj", _require(path, where, e, "bbox_obj"), 4)),
                    bbox_visib=tuple(int(v) for v in _floats(path, f"{where} bbox_visib", _require(path, where, e, "bbox_visib"), 4)),
                    px_count_all=int(_require(path, where, e, "px_count_all")),
                    px_count_valid=int(e.get("px_count_valid", -1)),
                    px_count_visib=int(_require(path, where, e, "px_count_visib")),
                    visib_fract=float(_require(path, where, e, "visib_fract")),
                ))
            except (TypeError, ValueError) as err:
                if str(err).startswith(str(path)):
                    raise
                raise ValueError(f"{path}: {where}: {err}") from None
        out[im_id] = lst
    return out


# ---- models -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class ModelInfo:
    """One object's entry of ``models_info.json``, in metres."""

    diameter_m: float
    """Largest distance between two model points."""
    min_m: np.ndarray
    """(3,) bounding-box corner (min_x, min_y, min_z)."""
    size_m: np.ndarray
    """(3,) bounding-box size."""
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    """4x4 model-frame transforms (translation in metres) that leave the object looking the same."""
    symmetries_continuous: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    """(axis (3,), offset_m (3,)) pairs: any rotation about the axis through the offset point."""

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)


def read_models_info(path: str | Path) -> dict[int, ModelInfo]:
    """Read ``models_info.json`` -> ``{obj_id: ModelInfo}`` (mm converted to metres)."""
    path = Path(path)
    out: dict[int, ModelInfo] = {}
    for obj_id, e in _keyed(path, "object"):
        where = f"object {obj_id}"
        diam = _floats(path, f"{where} diameter", _require(path, where, e, "diameter"), 1)[0]
        if diam <= 0:
            raise ValueError(f"{path}: {where}: diameter must be positive, got {diam}")
        mins = np.array([float(e.get(k, np.nan)) for k in ("min_x", "min_y", "min_z")])
        sizes = np.array([float(e.get(k, np.nan)) for k in ("size_x", "size_y", "size_z")])
        disc = []
        for i, s in enumerate(e.get("symmetries_discrete", []) or []):
            T = _floats(path, f"{where} symmetries_discrete[{i}]", s, 16).reshape(4, 4).copy()
            T[:3, 3] *= MM_TO_M  # mm -> m
            disc.append(T)
        cont = []
        for i, s in enumerate(e.get("symmetries_continuous", []) or []):
            w = f"{where} symmetries_continuous[{i}]"
            axis = _floats(path, f"{w} axis", _require(path, w, s, "axis"), 3)
            if np.linalg.norm(axis) < 1e-9:
                raise ValueError(f"{path}: {w}: axis must be non-zero")
            offset = _floats(path, f"{w} offset", s.get("offset", [0, 0, 0]), 3) * MM_TO_M
            cont.append((axis / np.linalg.norm(axis), offset))
        out[obj_id] = ModelInfo(diameter_m=float(diam) * MM_TO_M, min_m=mins * MM_TO_M,
                                size_m=sizes * MM_TO_M, symmetries_discrete=tuple(disc),
                                symmetries_continuous=tuple(cont))
    return out


@dataclass(frozen=True)
class Target:
    """One evaluation target (``test_targets_bop19.json``): ``inst_count`` instances of ``obj_id``."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def read_test_targets(path: str | Path) -> list[Target]:
    """Read a BOP test targets file (list of {scene_id, im_id, obj_id, inst_count})."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, list):
        raise ValueError(f"{path}: expected a list of targets")
    out = []
    for i, e in enumerate(d):
        vals = [_require(path, f"target {i}", e, k) for k in ("scene_id", "im_id", "obj_id")]
        try:
            t = Target(*(int(v) for v in vals), int(e.get("inst_count", 1)))
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: target {i}: bad id ({err})") from None
        if t.inst_count < 1:
            raise ValueError(f"{path}: target {i}: inst_count must be >= 1, got {t.inst_count}")
        out.append(t)
    return out
