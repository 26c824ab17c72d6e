"""Where the objects of a dataset come from: a model in its object frame plus ``T_world_obj``.

Sources (``presim gen-bop --objects``):

- *(default)* the objects stored with the scene (``scene.objects``; the built-in sample scene has
  some): PLY meshes in metres.
- ``bop:DIR``: a BOP scene folder (``DIR/scene_gt.json``, ``DIR/scene_camera.json``; models in mm in
  the nearest ``models/`` folder above it). Poses are per image (``T_cam_obj``); the image is
  located in the PreSim scene by its frame id (trailing number = BOP ``im_id``), or, when
  ``scene_camera.json`` has ``cam_R_w2c``/``cam_t_w2c``, by that world pose mapped through the
  world-frame changes the importer recorded (``scene.meta.transforms``).
- ``ycbv:DIR``: YCB-Video frames (``DIR/data/NNNNNN-meta.mat``: ``poses`` 3x4xN model-to-camera in
  metres, ``cls_indexes`` 1-based into the sorted ``DIR/models/*`` folders, each with
  ``points.xyz`` point models in metres); frames matched by number.
- a JSON file::

      {"objects": [{"obj_id": 1, "name": "mug", "model": "mug.ply", "unit": "m",
                    "T_world_obj": [[...4x4...]], "symmetric": false}]}

  (``model`` relative to the JSON's folder; ``unit`` of the model file, ``m`` by default;
  ``T_world_obj`` in metres; optional ``symmetries_discrete``: BOP-style 16 numbers, translation in
  the model's unit; optional ``symmetries_continuous``: ``[{"axis": [x, y, z], "offset": [x, y, z]}]``,
  offset in the model's unit).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.capture.scene import Scene, SceneError
from presim.capture.store import model_abspath
from presim.datasets.objects import ObjectModel, load_model, symmetries_of
from presim.formats.bop import read_models_info, read_scene_camera, read_scene_gt
from presim.geometry import check_rigid, compose, invert, make_pose

__all__ = ["PlacedObject", "read_json_items", "objects_from_scene", "objects_from_json", "objects_from_bop",
           "objects_from_ycbv", "resolve_objects"]


@dataclass(frozen=True)
class PlacedObject:
    """An object model placed in the scene's world."""

    model: ObjectModel
    T_world_obj: np.ndarray
    """4x4 object-to-world pose, metres."""

    @property
    def obj_id(self) -> int:
        return self.model.obj_id


def objects_from_scene(scene: Scene) -> list[PlacedObject]:
    """Objects stored with a saved scene (models in metres)."""
    out = []
    for o in scene.objects:
        p = model_abspath(scene, o)
        if p is None:
            raise SceneError(f"{scene.path}: object {o.obj_id} ({o.name}) has no model file")
        cont = [(o.symmetry_axis, (0.0, 0.0, 0.0))] if o.symmetry_axis else []
        m = load_model(p, o.obj_id, name=o.name, unit="m", symmetries_continuous=cont)
        if o.symmetric:
            m = _with_flag(m)
        out.append(PlacedObject(m, check_rigid(o.T_world_obj, f"{scene.path}: T_world_obj of object {o.obj_id}")))
    return out


def _with_flag(m: ObjectModel) -> ObjectModel:
    from dataclasses import replace

    return replace(m, symmetric_flag=True)


def _frame_number(frame_id: str) -> int | None:
    m = re.search(r"(\d+)(?!.*\d)", frame_id)
    return int(m.group(1)) if m else None


def _frame_index(scene: Scene, number: int, what: str) -> int:
    """Position of the scene frame whose id ends with ``number`` (e.g. ``000003``, ``frame-3``)."""
    hits = [i for i, f in enumerate(scene.frame_ids) if _frame_number(f) == number]
    if len(hits) != 1:
        raise SceneError(f"{what}: image {number} is {'ambiguous' if hits else 'not'} among the scene's frames "
                         f"(frame ids like {scene.frame_ids[:3]}); import the same capture the poses belong to")
    return hits[0]


def _world_from_transforms(scene: Scene) -> np.ndarray:
    T = np.eye(4)
    for t in scene.meta.transforms:
        T = compose(np.asarray(t.T_new_old, dtype=np.float64), T)
    return T


def read_json_items(path: Path, key: str, what: str, noun: str) -> list:
    """The non-empty list of a user JSON file that is either ``{key: [...]}`` or a bare list;
    ``FileNotFoundError`` ("<what> not found") / ``ValueError`` naming the file otherwise."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None
    items = d.get(key) if isinstance(d, dict) else d
    if not isinstance(items, list) or not items:
        raise ValueError(f"{path}: expected {{'{key}': [...]}} with at least one {noun}")
    return items


def objects_from_json(path: str | Path, scene: Scene | None = None) -> list[PlacedObject]:
    """Objects from a user JSON file (see the module docstring)."""
    path = Path(path)
    items = read_json_items(path, "objects", "objects JSON", "object")
    out = []
    for k, it in enumerate(items):
        where = f"{path}: objects[{k}]"
        try:
            out.append(_object_from_json(it, where, path.parent))
        except (ValueError, TypeError, KeyError) as e:
            msg = str(e)
            raise ValueError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return out


def _object_from_json(it, where: str, folder: Path) -> PlacedObject:
    if not isinstance(it, dict):
        raise ValueError(f"{where}: expected an object (dict), got {type(it).__name__}")
    for key in ("obj_id", "model", "T_world_obj"):
        if key not in it:
            raise ValueError(f"{where}: missing field '{key}'")
    unit = it.get("unit", "m")
    s = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}.get(unit)
    if s is None:
        raise ValueError(f"{where}: unknown unit {unit!r}")
    try:
        obj_id = int(it["obj_id"])
    except (TypeError, ValueError):
        raise ValueError(f"{where}: obj_id must be an integer, got {it['obj_id']!r}") from None
    syms = []
    for j, v in enumerate(it.get("symmetries_discrete", [])):
        a = np.asarray(v, dtype=np.float64)
        if a.size != 16:
            raise ValueError(f"{where}: symmetries_discrete[{j}] must have 16 numbers (4x4), got {a.size}")
        T = a.reshape(4, 4).copy()
        T[:3, 3] *= s
        syms.append(T)
    cont = []
    for j, c in enumerate(it.get("symmetries_continuous", [])):
        axis = np.asarray(c.get("axis", ()) if isinstance(c, dict) else (), dtype=np.float64)
        off = np.asarray(c.get("offset", (0, 0, 0)) if isinstance(c, dict) else (), dtype=np.float64)
        if axis.shape != (3,) or off.shape != (3,) or not np.linalg.norm(axis) > 0:
            raise ValueError(f"{where}: symmetries_continuous[{j}] must be {{'axis': [x, y, z], 'offset': [x, y, z]}}")
        cont.append((tuple(axis / np.linalg.norm(axis)), tuple(off * s)))
    model_path = Path(it["model"])
    if not model_path.is_absolute():
        model_path = folder / model_path
    m = load_model(model_path, obj_id, name=str(it.get("name", "")), unit=unit,
                   symmetries_discrete=syms, symmetries_continuous=cont)
    if it.get("symmetric"):
        m = _with_flag(m)
    Tw = it["T_world_obj"]
    if isinstance(Tw, dict):
        Tw = make_pose(np.asarray(Tw["R"], dtype=np.float64).reshape(3, 3), np.asarray(Tw["t"], dtype=np.float64))
    return PlacedObject(m, check_rigid(np.asarray(Tw, dtype=np.float64), f"{where}: T_world_obj"))


def _find_models_dir(start: Path) -> Path:
    for p in [start, *start.parents][:4]:
        if (p / "models").is_dir():
            return p / "models"
    raise FileNotFoundError(f"{start}: no BOP models/ folder found in it or its 3 parent folders")


def objects_from_bop(scene_folder: str | Path, scene: Scene) -> list[PlacedObject]:
    """Objects of a BOP scene placed in ``scene``'s world (see the module docstring)."""

    sdir = Path(scene_folder)
    if not (sdir / "scene_gt.json").is_file():
        raise FileNotFoundError(f"{sdir / 'scene_gt.json'}: not a BOP scene folder")
    gts = read_scene_gt(sdir / "scene_gt.json")
    cams = read_scene_camera(sdir / "scene_camera.json") if (sdir / "scene_camera.json").is_file() else {}
    mdir = _find_models_dir(sdir)
    info = read_models_info(mdir / "models_info.json") if (mdir / "models_info.json").is_file() else {}
    T_world_bopworld = _world_from_transforms(scene)
    placed: dict[int, PlacedObject] = {}
    for im_id in sorted(gts):
        for inst in gts[im_id]:
            if inst.obj_id in placed:
                continue  # first image showing the object fixes its world pose
            cam = cams.get(im_id)
            if cam is not None and cam.T_cam_world is not None:
                T_world_cam = compose(T_world_bopworld, invert(cam.T_cam_world))
            else:
                T_world_cam = scene.T_world_cam[_frame_index(scene, im_id, str(sdir))]
            syms_d, syms_c = symmetries_of(info.get(inst.obj_id))
            m = load_model(mdir / f"obj_{inst.obj_id:06d}.ply", inst.obj_id, unit="mm",
                           symmetries_discrete=syms_d, symmetries_continuous=syms_c)
            placed[inst.obj_id] = PlacedObject(m, compose(T_world_cam, inst.T_cam_obj))
    if not placed:
        raise ValueError(f"{sdir / 'scene_gt.json'}: no object instances")
    return [placed[k] for k in sorted(placed)]


def objects_from_ycbv(root: str | Path, scene: Scene) -> list[PlacedObject]:
    """Objects of YCB-Video frames (``root/data/*-meta.mat``, ``root/models/*/points.xyz``)."""
    import scipy.io

    root = Path(root)
    metas = sorted((root / "data").glob("*-meta.mat"))
    if not metas:
        raise FileNotFoundError(f"{root / 'data'}: no *-meta.mat files (YCB-Video layout expected)")
    model_dirs = sorted(p for p in (root / "models").iterdir() if p.is_dir()) if (root / "models").is_dir() else []
    if not model_dirs:
        raise FileNotFoundError(f"{root / 'models'}: no model folders")
    placed: dict[int, PlacedObject] = {}
    for meta_path in metas:
        try:
            meta = scipy.io.loadmat(meta_path)
        except Exception as e:  # scipy raises several types for corrupt files
            raise ValueError(f"{meta_path}: unreadable meta.mat ({e})") from None
        for key in ("poses", "cls_indexes"):
            if key not in meta:
                raise ValueError(f"{meta_path}: missing '{key}'")
        cls = np.asarray(meta["cls_indexes"]).ravel().astype(int)
        poses = np.asarray(meta["poses"], dtype=np.float64).reshape(3, 4, -1)
        if poses.shape[2] != len(cls):
            raise ValueError(f"{meta_path}: {poses.shape[2]} poses for {len(cls)} classes")
        number = int(meta_path.name.split("-")[0])
        idx = None
        for k, c in enumerate(cls):
            if c in placed:
                continue
            if not 1 <= c <= len(model_dirs):
                raise ValueError(f"{meta_path}: class index {c} outside 1..{len(model_dirs)}")
            if idx is None:
                idx = _frame_index(scene, number, str(meta_path))
            T_cam_obj = make_pose(poses[:, :3, k], poses[:, 3, k])
            mdir = model_dirs[c - 1]
            mp = mdir / "points.xyz"
            if not mp.is_file():
                cands = sorted(mdir.glob("*.ply")) + sorted(mdir.glob("*.obj"))
                if not cands:
                    raise FileNotFoundError(f"{mdir}: no points.xyz or mesh")
                mp = cands[0]
            m = load_model(mp, int(c), name=mdir.name, unit="m")
            placed[int(c)] = PlacedObject(m, compose(scene.T_world_cam[idx], T_cam_obj))
    return [placed[k] for k in sorted(placed)]


def resolve_objects(scene: Scene, spec: str | None) -> list[PlacedObject]:
    """Objects for ``gen-bop``: ``None`` = the scene's own, ``bop:DIR``, ``ycbv:DIR`` or a JSON path."""
    if spec is None:
        objs = objects_from_scene(scene)
        if not objs:
            raise SceneError(f"{scene.path}: the scene has no objects; pass --objects JSON|bop:DIR|ycbv:DIR")
    elif spec.startswith("bop:"):
        objs = objects_from_bop(spec[4:], scene)
    elif spec.startswith("ycbv:"):
        objs = objects_from_ycbv(spec[5:], scene)
    else:
        objs = objects_from_json(spec, scene)
    ids = [o.obj_id for o in objs]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{spec or scene.path}: object ids must be unique, got {ids}")
    return objs
