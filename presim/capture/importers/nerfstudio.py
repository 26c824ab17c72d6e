"""nerfstudio ``transforms.json`` captures (with depth).

Fields read (shared at the top level, or per frame, per-frame values win)::

    fl_x fl_y cx cy w h                 pixels; camera_model PINHOLE | OPENCV (k1 k2 p1 p2 [k3]) | SIMPLE_PINHOLE
    frames[i].file_path                 image, relative to the json's folder
    frames[i].transform_matrix          4x4 camera-to-world, OpenGL camera (x right, y up, z backward)
    frames[i].depth_file_path           depth image: 16-bit PNG or .npy
    depth_unit_scale_factor             metres per stored depth unit (nerfstudio's default 1e-3 = mm),
                                        applied to PNG and .npy alike, as nerfstudio does

Traps handled at this border:
- OpenGL -> OpenCV camera: ``T_world_cv = T_world_gl @ diag(1, -1, -1, 1)``.
- nerfstudio (like COLMAP) puts pixel (0, 0) at the pixel corner: ``cx - 0.5``, ``cy - 0.5``.
- ``applied_transform`` / ``applied_scale`` of a ns-process-data output are already in the poses; a
  scale != 1 means the depth no longer matches the poses, so it is an error.
- Frames without ``depth_file_path`` are an error (PreSim needs depth for every frame).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, Undistortion, checked_pose, image_size_wh, read_depth_camera, require_file, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta
from presim.geometry import T_CV_FROM_GL, Intrinsics, compose

NAME = "nerfstudio"
VERSION = "1"
DEFAULT_DEPTH_SCALE = 1e-3
_INTR_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "p1", "p2", "camera_model")


def find_json(src: Path) -> Path | None:
    if src.is_file() and src.suffix == ".json":
        return src
    if src.is_dir() and (src / "transforms.json").is_file():
        return src / "transforms.json"
    return None


def detect(src: Path) -> bool:
    return find_json(src) is not None


def _intrinsics(d: dict, where: str) -> tuple[Intrinsics, Undistortion | None]:
    model = d.get("camera_model", "OPENCV")
    if model not in ("PINHOLE", "OPENCV", "SIMPLE_PINHOLE"):
        raise SceneError(f"{where}: camera_model {model} is not supported (PINHOLE, OPENCV, SIMPLE_PINHOLE)")
    try:
        fx = float(d["fl_x"])
        fy = float(d.get("fl_y", fx))
        w, h = int(d["w"]), int(d["h"])
        cx, cy = float(d.get("cx", w / 2.0)), float(d.get("cy", h / 2.0))
    except KeyError as e:
        raise SceneError(f"{where}: missing intrinsics field {e}") from None
    except (TypeError, ValueError) as e:
        raise SceneError(f"{where}: bad intrinsics ({e})") from None
    # nerfstudio's pixel origin is the top-left corner (rays through i + 0.5); ours is the centre.
    try:
        K = Intrinsics(fx, fy, cx - 0.5, cy - 0.5, w, h)
    except ValueError as e:
        raise SceneError(f"{where}: {e}") from None
    dist = tuple(float(d.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3"))
    if model == "OPENCV" and any(dist):
        return K, Undistortion(K, dist, K)
    return K, None


def read(src: Path, every: int = 1, max_frames: int | None = None) -> Scene:
    src = Path(src)
    jpath = find_json(src)
    if jpath is None:
        raise SceneError(f"{src}: no transforms.json")
    try:
        meta = json.loads(jpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{jpath}: corrupt JSON ({e})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise SceneError(f"{jpath}: no 'frames' list")
    if abs(float(meta.get("applied_scale", 1.0)) - 1.0) > 1e-9:
        raise SceneError(f"{jpath}: applied_scale {meta['applied_scale']} != 1: poses were rescaled and no "
                         "longer match metric depth")
    root = jpath.parent
    scale = float(meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_SCALE))
    shared = {k: meta[k] for k in _INTR_KEYS if k in meta}
    frames = meta["frames"]
    sel = select_indices(len(frames), every, max_frames)
    ids, poses, Ks, undists, colors, depths = [], [], [], [], [], []
    cache: dict[tuple, tuple[Intrinsics, Undistortion | None]] = {}
    for i in sel:
        fr = frames[i]
        where = f"{jpath} frames[{i}]"
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{where}: needs file_path and transform_matrix")
        if "depth_file_path" not in fr:
            raise SceneError(f"{where}: no depth_file_path (PreSim needs depth for every frame)")
        intr = {**shared, **{k: fr[k] for k in _INTR_KEYS if k in fr}}
        key = tuple(sorted((k, str(v)) for k, v in intr.items()))
        if key not in cache:
            cache[key] = _intrinsics(intr, where)
        K, ud = cache[key]
        try:
            T_gl = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise SceneError(f"{where}: transform_matrix is not a 4x4 matrix of numbers") from None
        if T_gl.shape == (3, 4):
            T_gl = np.vstack([T_gl, [0, 0, 0, 1]])
        T_gl = checked_pose(T_gl, f"{where} transform_matrix")
        # OpenGL camera (y up, z back) -> OpenCV camera (y down, z forward).
        poses.append(compose(T_gl, T_CV_FROM_GL))
        cpath = require_file(root / fr["file_path"], "image")
        wh = image_size_wh(cpath)
        if wh != (K.width, K.height):
            raise SceneError(f"{cpath}: resolution {wh[0]}x{wh[1]} != w x h {K.width}x{K.height} in {jpath.name}")
        ids.append(Path(fr["file_path"]).stem)
        Ks.append(K)
        undists.append(ud)
        colors.append(cpath)
        depths.append(require_file(root / fr["depth_file_path"], "depth file"))
    if len(set(ids)) != len(ids):
        ids = [str(Path(frames[i]["file_path"]).with_suffix("")) for i in sel]

    def decode(raw: np.ndarray, path: Path) -> np.ndarray:
        return raw.astype(np.float32) * np.float32(scale)  # 0 stays 0; non-finite cleaned by the source

    depth_cam = read_depth_camera(root, depths[0])
    source = FileFrameSource(colors, depths, Ks, decode, undistortion=undists, depth_camera=depth_cam)
    # nerfstudio's optional per-frame "time" is normalised to [0, 1] (dynamic scenes), not seconds.
    stamps = np.array(sel, dtype=np.float64) / 30.0
    notes = (f"depth_unit_scale_factor {scale:g} m/unit", "OpenGL camera converted to OpenCV; cx, cy -0.5 px",
             "no timestamps in transforms.json: stamp = frame index / 30 s")
    if depth_cam is not None:
        notes += ("depth registered into the color camera at read (depth-intrinsics.txt + depth-to-color.txt)",)
    return Scene(ids, stamps, np.stack(poses), Ks, source,
                 SceneMeta(str(jpath.resolve()), NAME, VERSION, notes=notes))
