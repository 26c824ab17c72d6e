"""Readers for the BOP dataset format (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md).

BOP files are in millimetres; everything returned here is in **metres** (converted at this border),
except :class:`PlyModel` which keeps the file's units (BOP models are mm) and converts on request
with :meth:`PlyModel.scaled` / :func:`load_model_m`.

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

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from presim.geometry import Intrinsics, make_pose

__all__ = [
    "MM_TO_M",
    "BopCamera",
    "SceneCamera",
    "GtInstance",
    "GtInfo",
    "ModelInfo",
    "Target",
    "PlyModel",
    "read_camera_json",
    "read_scene_camera",
    "read_scene_gt",
    "read_scene_gt_info",
    "read_models_info",
    "read_test_targets",
    "load_ply",
    "load_model_m",
    "BopDataset",
]

MM_TO_M = 1e-3
"""BOP lengths are millimetres; multiply by this to get metres."""

# Rotations in BOP files are stored with ~8 decimals; anything further off than this is not a rotation.
_ROT_TOL = 1e-2


# ---- small helpers ----------------------------------------------------------------------------

def _load_json(path: str | Path):
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


def read_camera_json(path: str | Path) -> BopCamera:
    """Read a BOP ``camera.json`` (fx, fy, cx, cy, width, height, depth_scale)."""
    path = Path(path)
    d = _load_json(path)
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


def read_scene_camera(path: str | Path) -> dict[int, SceneCamera]:
    """Read ``scene_camera.json`` -> ``{im_id: SceneCamera}`` (translations converted to metres)."""
    path = Path(path)
    d = _load_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected an object keyed by image id")
    out: dict[int, SceneCamera] = {}
    for key, e in d.items():
        im_id = _int_key(path, key)
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


def read_scene_gt(path: str | Path) -> dict[int, list[GtInstance]]:
    """Read ``scene_gt.json`` -> ``{im_id: [GtInstance, ...]}`` in file order (the gt index)."""
    path = Path(path)
    d = _load_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected an object keyed by image id")
    out: dict[int, list[GtInstance]] = {}
    for key, insts in d.items():
        im_id = _int_key(path, key)
        if not isinstance(insts, list):
            raise ValueError(f"{path}: image {im_id}: expected a list of instances")
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


def read_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    """Read ``scene_gt_info.json`` -> ``{im_id: [GtInfo, ...]}``."""
    path = Path(path)
    d = _load_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected an object keyed by image id")
    out: dict[int, list[GtInfo]] = {}
    for key, insts in d.items():
        im_id = _int_key(path, key)
        if not isinstance(insts, list):
            raise ValueError(f"{path}: image {im_id}: expected a list of instances")
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
    d = _load_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected an object keyed by object id")
    out: dict[int, ModelInfo] = {}
    for key, e in d.items():
        obj_id = _int_key(path, key)
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
    d = _load_json(path)
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


# ---- PLY --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PlyModel:
    """A mesh or point cloud from a PLY file, in the file's units (BOP: mm)."""

    pts: np.ndarray
    """(N, 3) float64 vertex positions."""
    faces: np.ndarray | None = None
    """(F, 3) int64 triangle vertex indices (polygons are fan-triangulated), or None."""
    normals: np.ndarray | None = None
    """(N, 3) float64 vertex normals, or None."""
    colors: np.ndarray | None = None
    """(N, 3) uint8 RGB vertex colours, or None."""
    texture_uv: np.ndarray | None = None
    """(N, 2) float64 per-vertex texture coordinates, or None."""

    def scaled(self, factor: float) -> "PlyModel":
        """Same model with positions multiplied by ``factor`` (e.g. :data:`MM_TO_M`)."""
        return PlyModel(self.pts * factor, self.faces, self.normals, self.colors, self.texture_uv)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list = field(default_factory=list)  # (name, dtype) or (name, ("list", count_dtype, item_dtype))


def _parse_ply_header(path: Path, f) -> tuple[str, list[_PlyElement]]:
    if f.readline().strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[_PlyElement] = []
    while True:
        line = f.readline()
        if not line:
            raise ValueError(f"{path}: PLY header has no 'end_header'")
        parts = line.decode("ascii", errors="replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append(_PlyElement(parts[1], int(parts[2])))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element")
            if parts[1] == "list":
                if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY list types {parts[2:4]}")
                elements[-1].props.append((parts[4], ("list", _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]])))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {parts[1]!r}")
                elements[-1].props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements


def _triangulate(path: Path, polys: list[np.ndarray] | np.ndarray) -> np.ndarray:
    if isinstance(polys, np.ndarray):  # all polygons have the same size
        n = polys.shape[1]
        if n < 3:
            raise ValueError(f"{path}: faces with fewer than 3 vertices")
        return np.concatenate([polys[:, [0, i, i + 1]] for i in range(1, n - 1)], axis=0).astype(np.int64)
    tris = [p[[0, i, i + 1]] for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def load_ply(path: str | Path) -> PlyModel:
    """Load a PLY mesh/point cloud (ASCII, binary little- or big-endian) in the file's units.

    Reads vertex ``x y z`` (required), ``nx ny nz``, ``red green blue``, ``texture_u texture_v``
    and ``face vertex_indices`` (or ``vertex_index``). Other elements/properties are skipped.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    with open(path, "rb") as f:
        fmt, elements = _parse_ply_header(path, f)
        data = f.read()
    arrays: dict[str, dict[str, np.ndarray]] = {}
    faces_polys = None
    if fmt == "ascii":
        tokens = data.split()
        pos = 0
        for el in elements:
            has_list = any(isinstance(t, tuple) for _, t in el.props)
            if not has_list:
                n_props = len(el.props)
                chunk = tokens[pos: pos + el.count * n_props]
                if len(chunk) != el.count * n_props:
                    raise ValueError(f"{path}: truncated PLY ({el.name}: expected {el.count} rows)")
                vals = np.array(chunk, dtype=np.float64).reshape(el.count, n_props)
                pos += el.count * n_props
                arrays[el.name] = {name: vals[:, i] for i, (name, _) in enumerate(el.props)}
            else:
                rows_lists = []
                for _ in range(el.count):
                    for name, t in el.props:
                        if pos >= len(tokens):
                            raise ValueError(f"{path}: truncated PLY in element {el.name}")
                        if isinstance(t, tuple):
                            n = int(tokens[pos])
                            items = np.array(tokens[pos + 1: pos + 1 + n], dtype=np.int64)
                            if len(items) != n:
                                raise ValueError(f"{path}: truncated PLY in element {el.name}")
                            pos += 1 + n
                            if el.name == "face" and name in ("vertex_indices", "vertex_index"):
                                rows_lists.append(items)
                        else:
                            pos += 1
                if el.name == "face":
                    lens = {len(r) for r in rows_lists}
                    faces_polys = np.stack(rows_lists) if len(lens) == 1 else rows_lists
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        pos = 0
        for el in elements:
            has_list = any(isinstance(t, tuple) for _, t in el.props)
            if not has_list:
                dt = np.dtype([(name, end + t) for name, t in el.props])
                nbytes = dt.itemsize * el.count
                if pos + nbytes > len(data):
                    raise ValueError(f"{path}: truncated PLY ({el.name}: expected {el.count} rows)")
                rec = np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
                pos += nbytes
                arrays[el.name] = {name: rec[name].astype(np.float64) for name, _ in el.props}
                continue
            # Fast path: one list property whose length is the same for every row (triangle meshes).
            if len(el.props) == 1 and el.count > 0:
                name, (_, cdt, idt) = el.props[0]
                cdt, idt = np.dtype(end + cdt), np.dtype(end + idt)
                n0 = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                row = np.dtype([("n", cdt), ("v", idt, (n0,))])
                if pos + row.itemsize * el.count <= len(data):
                    rec = np.frombuffer(data, dtype=row, count=el.count, offset=pos)
                    if np.all(rec["n"] == n0):
                        pos += row.itemsize * el.count
                        if el.name == "face":
                            faces_polys = rec["v"].astype(np.int64)
                        continue
            polys = []
            for _ in range(el.count):
                for name, t in el.props:
                    if isinstance(t, tuple):
                        cdt, idt = np.dtype(end + t[1]), np.dtype(end + t[2])
                        n = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                        pos += cdt.itemsize
                        items = np.frombuffer(data, dtype=idt, count=n, offset=pos).astype(np.int64)
                        pos += idt.itemsize * n
                        if el.name == "face" and name in ("vertex_indices", "vertex_index"):
                            polys.append(items)
                    else:
                        pos += np.dtype(t).itemsize
            if el.name == "face":
                faces_polys = polys
    v = arrays.get("vertex")
    if v is None or not all(k in v for k in ("x", "y", "z")):
        raise ValueError(f"{path}: PLY has no vertex element with x, y, z")
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1)
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: vertex positions contain non-finite values")
    normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1) if all(k in v for k in ("nx", "ny", "nz")) else None
    colors = None
    if all(k in v for k in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).clip(0, 255).astype(np.uint8)
    uv = np.stack([v["texture_u"], v["texture_v"]], axis=1) if all(k in v for k in ("texture_u", "texture_v")) else None
    faces = None
    if faces_polys is not None and len(faces_polys):
        faces = _triangulate(path, faces_polys)
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise ValueError(f"{path}: face indices out of range [0, {len(pts)})")
    return PlyModel(pts=pts, faces=faces, normals=normals, colors=colors, texture_uv=uv)


def load_model_m(path: str | Path) -> PlyModel:
    """Load a BOP model PLY (millimetres) and return it in metres."""
    return load_ply(path).scaled(MM_TO_M)  # BOP mm -> metres


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
    def load_model(self, obj_id: int, eval: bool = False) -> PlyModel:
        """Model of ``obj_id`` in **metres** (``eval``: from models_eval/ when present)."""
        p = self.model_path(obj_id, eval=eval)
        return self._cached(("model", str(p)), load_model_m, p)

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
        from presim.io_utils import read_image
        return read_image(self.image_path(scene_id, im_id, "rgb"), kind="color")

    def read_depth_m(self, scene_id: int, im_id: int) -> np.ndarray:
        """float32 (H, W) z-depth in metres, 0 = invalid (``png * depth_scale / 1000``)."""
        from presim.io_utils import read_image
        raw = read_image(self.image_path(scene_id, im_id, "depth"), kind="depth")
        scale = self.scene_camera(scene_id)[im_id].depth_scale
        return (raw.astype(np.float32) * np.float32(scale * MM_TO_M))  # BOP mm x depth_scale -> m

    def read_mask(self, scene_id: int, im_id: int, gt_idx: int, visib: bool = True) -> np.ndarray:
        """bool (H, W) mask of instance ``gt_idx``."""
        from presim.io_utils import read_image
        return read_image(self.mask_path(scene_id, im_id, gt_idx, visib), kind="mask") > 0
