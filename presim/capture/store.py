"""The saved scene: a documented, versioned folder that reloads losslessly and lazily.

Layout (format ``presim-scene``, version 1; see docs/scene-format.md)::

    SCENE/
      scene.json            metadata, per-frame ids / stamps / poses / intrinsics, floor, gravity, objects
      color.npy             uint8   (N, H, W, 3)  RGB            -- memory-mapped on load
      depth.npy             float32 (N, H, W)     metres, 0 = invalid (raw, as imported)
      depth_refined.npy     float32 (N, H, W)     optional, written by ``presim refine``
      depth_fused.npy       float32 (N, H, W)     optional, written by ``presim fuse`` (needs depth_refined)
      depth_completed.npy   float32 (N, H, W)     optional, written by ``presim complete`` (0 = not completed)
      photometric.json      per-frame colour transforms, optional, written by ``presim photometric``
      render_filter.json    the renderer's fitted reconstruction filter, optional, written by ``presim fit-filter``
      points_xyz.npy        float32 (M, 3)        world-frame colored point cloud
      points_rgb.npy        uint8   (M, 3)
      objects/              object models (PLY/OBJ/xyz), metres, object frame

Raw ``.npy`` arrays are lossless and memory-mappable: 1000 frames at 1280x720 are 3.7 GB of depth
but only the frames touched are paged in. Saving streams frame by frame into the arrays.
"""

from __future__ import annotations

import json
import mmap
import shutil
from pathlib import Path

import numpy as np

from presim.capture.calibration import PhotometricCalib
from presim.capture.scene import (
    ArrayFrameSource, FloorPlane, PointCloud, Scene, SceneError, SceneMeta, SceneObject, check_scene_geometry,
)
from presim.geometry import Intrinsics, unproject_depth
from presim.io_utils import (
    DiskFullError, atomic_dir, atomic_write_json, disk_full_error, free_disk_bytes, open_npy_for_writing, progress,
)

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "save_scene", "load_scene", "fuse_point_cloud", "is_scene_dir",
           "set_has_refined_depth", "set_has_fused_depth",
           "REFINED_POSES_FILE", "POSE_CHOICES", "save_refined_poses", "read_refined_poses",
           "PHOTOMETRIC_FILE", "save_photometric", "saved_scene_bytes", "RENDER_FILTER_FILE", "save_render_filter", "unmap_pages"]

PHOTOMETRIC_FILE = "photometric.json"
RENDER_FILTER_FILE = "render_filter.json"
MAX_FILTER_SIGMA_PX = 8.0

FORMAT_NAME = "presim-scene"
FORMAT_VERSION = 1
REFINED_POSES_FILE = "poses_refined.json"
POSE_CHOICES = ("auto", "given", "refined")


def is_scene_dir(path: str | Path) -> bool:
    return (Path(path) / "scene.json").is_file()


def fuse_point_cloud(scene: Scene, voxel_m: float = 0.01, stride: int = 4,
                     max_points: int = 2_000_000, refined: bool = False, batch_frames: int = 16) -> PointCloud:
    """Colored point cloud of the whole scene: every ``stride``-th pixel of every frame, unprojected
    to the world and reduced to one point (first seen) per ``voxel_m`` voxel.

    Frames are deduplicated in batches of ``batch_frames`` against the voxels seen so far, so memory
    holds the fused cloud plus one batch of frames' points, whatever the number of frames."""
    xyz_all: list[np.ndarray] = []
    rgb_all: list[np.ndarray] = []
    seen: np.ndarray = np.empty(0, dtype=np.int64)
    batch: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def flush() -> None:
        nonlocal seen
        if not batch:
            return
        key = np.concatenate([b[0] for b in batch])
        pts = np.concatenate([b[1] for b in batch])
        rgb = np.concatenate([b[2] for b in batch])
        batch.clear()
        key, first = np.unique(key, return_index=True)  # first occurrence in frame order
        new = ~np.isin(key, seen, assume_unique=True)
        xyz_all.append(pts[first[new]])
        rgb_all.append(rgb[first[new]])
        seen = np.union1d(seen, key[new])

    for i in progress(range(len(scene)), desc="point cloud", unit="frame"):
        f = scene.frame(i, refined=refined)
        pts, mask = unproject_depth(f.K, f.depth_m, f.T_world_cam, stride=stride)
        if len(pts) == 0:
            continue
        q = np.floor(pts / voxel_m).astype(np.int64)
        # 21 bits per axis: +-10 km at 1 cm voxels.
        key = ((q[:, 0] + (1 << 20)) << 42) | ((q[:, 1] + (1 << 20)) << 21) | (q[:, 2] + (1 << 20))
        batch.append((key, pts, f.color[::stride, ::stride][mask]))
        if len(batch) >= batch_frames:
            flush()
    flush()
    if not xyz_all:
        return PointCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8))
    xyz = np.concatenate(xyz_all).astype(np.float32)
    rgb = np.concatenate(rgb_all).astype(np.uint8)
    if len(xyz) > max_points:
        keep = np.random.default_rng(0).choice(len(xyz), max_points, replace=False)
        keep.sort()
        xyz, rgb = xyz[keep], rgb[keep]
    return PointCloud(xyz, rgb)


def _frames_json(scene: Scene) -> list[dict]:
    return [
        {
            "frame_id": scene.frame_ids[i],
            "stamp_s": float(scene.stamps_s[i]),
            "T_world_cam": scene.T_world_cam[i].tolist(),
            "intrinsics": scene.intrinsics[i].to_dict(),
        }
        for i in range(len(scene))
    ]


def save_scene(scene: Scene, dst: str | Path, overwrite: bool = False,
               voxel_m: float = 0.01) -> Path:
    """Write ``scene`` to the folder ``dst`` atomically (built in ``dst.partial``, then renamed).

    Frames stream one at a time from the scene's source, so a capture never needs to fit in RAM.
    Missing point clouds are fused here (``voxel_m``). Object models are copied into ``objects/``.
    Returns ``dst``.
    """
    dst = Path(dst)
    n, h, w = len(scene), scene.height, scene.width
    needed = saved_scene_bytes(scene)
    free = free_disk_bytes(dst.parent)
    if needed > free:  # refuse before writing anything (an existing dst stays as it is)
        raise DiskFullError(dst, needed, free)
    try:
        return _save_scene(scene, dst, overwrite, voxel_m, n, h, w)
    except DiskFullError:
        raise
    except OSError as e:  # ENOSPC of a file written after the arrays (the partial folder is gone)
        raise disk_full_error(e, dst, needed) from None


def saved_scene_bytes(scene: Scene) -> int:
    """Bytes of the arrays :func:`save_scene` writes (color, depth, refined / fused depth, points)
    plus 1 MiB for scene.json and headers: checked against the free disk space before saving."""
    px = len(scene) * scene.height * scene.width
    n_depth = 1 + sum(a is not None for a in (scene.depth_refined, scene.depth_fused, scene.depth_completed))
    n_points = len(scene.points) if scene.points is not None else min(px // 16, 2_000_000)
    return int(px * (3 + 4 * n_depth) + 15 * n_points + 2**20)


def _save_scene(scene: Scene, dst: Path, overwrite: bool, voxel_m: float, n: int, h: int, w: int) -> Path:
    with atomic_dir(dst, overwrite=overwrite) as tmp:
        color = open_npy_for_writing(tmp / "color.npy", np.uint8, (n, h, w, 3))
        depth = open_npy_for_writing(tmp / "depth.npy", np.float32, (n, h, w))
        for i in progress(range(n), desc="saving frames", unit="frame"):
            c, d = scene.frames.load(i)
            if c.shape != (h, w, 3) or c.dtype != np.uint8:
                raise SceneError(f"frame {scene.frame_ids[i]}: color must be uint8 {h}x{w}x3, got {c.dtype} {c.shape}")
            if d.shape != (h, w) or d.dtype != np.float32:
                raise SceneError(f"frame {scene.frame_ids[i]}: depth must be float32 {h}x{w}, got {d.dtype} {d.shape}")
            color[i] = c
            depth[i] = d
        color.flush()
        depth.flush()
        del color, depth
        if scene.depth_refined is not None:
            ref = open_npy_for_writing(tmp / "depth_refined.npy", np.float32, (n, h, w))
            for i in range(n):
                ref[i] = scene.depth_refined[i]
            ref.flush()
            del ref
        for name, arr in (("depth_fused", scene.depth_fused), ("depth_completed", scene.depth_completed)):
            if arr is not None:
                out = open_npy_for_writing(tmp / f"{name}.npy", np.float32, (n, h, w))
                for i in range(n):
                    out[i] = arr[i]
                out.flush()
                del out

        if scene.photometric is not None:
            atomic_write_json(tmp / PHOTOMETRIC_FILE, scene.photometric.to_json(), indent=1)
        if scene.render_filter_sigma_px is not None:
            atomic_write_json(tmp / RENDER_FILTER_FILE, {"sigma_px": scene.render_filter_sigma_px}, indent=1)

        saved = load_scene(tmp, _skip_points=True)
        saved = _with_arrays(scene, saved)
        points = scene.points if scene.points is not None else fuse_point_cloud(saved, voxel_m=voxel_m)
        np.save(tmp / "points_xyz.npy", points.xyz.astype(np.float32))
        np.save(tmp / "points_rgb.npy", points.rgb.astype(np.uint8))

        objects_json = []
        if scene.objects:
            (tmp / "objects").mkdir()
        for obj in scene.objects:
            model_rel = None
            if obj.model_path is not None:
                src = Path(obj.model_path)
                if not src.is_absolute() and scene.path is not None:
                    src = scene.path / src
                if not src.is_file():
                    raise SceneError(f"object {obj.name}: model file {src} not found")
                model_rel = f"objects/obj_{obj.obj_id:06d}{''.join(src.suffixes)}"
                shutil.copyfile(src, tmp / model_rel)
            objects_json.append({
                "obj_id": int(obj.obj_id), "name": obj.name, "T_world_obj": np.asarray(obj.T_world_obj).tolist(),
                "model_path": model_rel, "symmetric": bool(obj.symmetric),
                **({"symmetry_axis": [float(a) for a in obj.symmetry_axis]} if obj.symmetry_axis else {}),
            })

        header = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "num_frames": n,
            "width": w,
            "height": h,
            "meta": scene.meta.to_dict(),
            "floor": None if scene.floor is None else {
                "normal": list(scene.floor.normal), "offset": scene.floor.offset,
                "inlier_frac": scene.floor.inlier_frac},
            "gravity_world": np.asarray(scene.gravity_world, dtype=float).tolist(),
            "has_refined_depth": scene.depth_refined is not None,
            "has_fused_depth": scene.depth_fused is not None,
            "objects": objects_json,
            "frames": _frames_json(scene),
        }
        # scene.json last: a folder without it is never taken for a scene.
        atomic_write_json(tmp / "scene.json", header, indent=1)
    return dst


def set_has_refined_depth(path: str | Path) -> None:
    """Update ``scene.json``'s ``has_refined_depth`` to whether ``depth_refined.npy`` exists
    (``presim refine`` calls this once the file is complete). Atomic rewrite of scene.json."""
    import json

    path = Path(path)
    hdr = json.loads((path / "scene.json").read_text())
    present = (path / "depth_refined.npy").is_file()
    if hdr.get("has_refined_depth") != present:
        hdr["has_refined_depth"] = present
        atomic_write_json(path / "scene.json", hdr, indent=1)


def set_has_fused_depth(path: str | Path) -> None:
    """Update ``scene.json``'s ``has_fused_depth`` to whether ``depth_fused.npy`` exists (``presim
    fuse`` calls this once the file is in place). Atomic rewrite of scene.json."""
    import json

    path = Path(path)
    hdr = json.loads((path / "scene.json").read_text())
    present = (path / "depth_fused.npy").is_file()
    if hdr.get("has_fused_depth") != present:
        hdr["has_fused_depth"] = present
        atomic_write_json(path / "scene.json", hdr, indent=1)


def save_photometric(path: str | Path, calib) -> Path:
    """Write a :class:`~presim.capture.calibration.PhotometricCalib` into the saved scene at ``path``
    as ``photometric.json`` (atomic; the images are never touched). Its frame ids must be the
    scene's. Returns the file."""
    path = Path(path)
    hdr_path = path / "scene.json"
    if not hdr_path.is_file():
        raise SceneError(f"{path}: not a PreSim scene (no scene.json)")
    ids = [f["frame_id"] for f in json.loads(hdr_path.read_text())["frames"]]
    if list(calib.frame_ids) != ids:
        raise SceneError(f"{path}: photometric calibration frame ids do not match the scene's frames")
    out = path / PHOTOMETRIC_FILE
    atomic_write_json(out, calib.to_json(), indent=1)
    return out


def save_render_filter(path: str | Path, sigma_px: float, fit: dict | None = None) -> Path:
    """Write the renderer's reconstruction filter (sigma in pixels at the capture's sampling, and what the
    fit measured) into the saved scene at ``path`` as ``render_filter.json`` (atomic). Returns the file."""
    path = Path(path)
    if not (path / "scene.json").is_file():
        raise SceneError(f"{path}: not a PreSim scene (no scene.json)")
    if not 0.0 <= float(sigma_px) <= MAX_FILTER_SIGMA_PX:
        raise SceneError(f"{path}: render filter sigma must be in [0, {MAX_FILTER_SIGMA_PX}] px, got {sigma_px}")
    out = path / RENDER_FILTER_FILE
    atomic_write_json(out, {"sigma_px": float(sigma_px), **({"fit": fit} if fit else {})}, indent=1)
    return out


def _load_render_filter(path: Path) -> float | None:
    f = path / RENDER_FILTER_FILE
    if not f.is_file():
        return None
    try:
        sigma = json.loads(f.read_text())["sigma_px"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise SceneError(f"{f}: corrupt render filter ({type(e).__name__}: {e}); rerun presim fit-filter") from None
    if not isinstance(sigma, (int, float)) or not 0.0 <= sigma <= MAX_FILTER_SIGMA_PX:
        raise SceneError(f"{f}: sigma_px must be a number in [0, {MAX_FILTER_SIGMA_PX}], got {sigma!r}")
    return float(sigma)


def _load_photometric(path: Path) -> PhotometricCalib | None:
    f = path / PHOTOMETRIC_FILE
    if not f.is_file():
        return None
    try:
        return PhotometricCalib.from_json(json.loads(f.read_text()), str(f))
    except json.JSONDecodeError as e:
        raise SceneError(f"{f}: corrupt JSON ({e})") from None
    except ValueError as e:
        raise SceneError(str(e)) from None


def _with_arrays(meta_scene: Scene, array_scene: Scene) -> Scene:
    from dataclasses import replace

    return replace(meta_scene, frames=array_scene.frames, path=None)


def _load_array(path: Path, mmap: bool = True) -> np.ndarray:
    """``np.load`` whose errors name the file (truncated or corrupt arrays of a damaged scene)."""
    if not path.is_file():
        raise SceneError(f"{path}: missing (damaged scene folder?)")
    try:
        return np.load(path, mmap_mode="r" if mmap else None)
    except (ValueError, OSError, EOFError) as e:
        raise SceneError(f"{path}: unreadable array ({e}); the scene folder is damaged") from None


def load_scene(path: str | Path, _skip_points: bool = False, poses: str = "auto") -> Scene:
    """Load a saved scene; pixel arrays are memory-mapped (read-only), nothing else is read eagerly.

    ``poses``: ``"auto"`` (default) uses the refined poses of ``presim align`` when the scene has them
    (``poses_refined.json``), else the given ones; ``"given"`` always the capture's poses;
    ``"refined"`` the refined ones or an error when there are none. ``scene.poses_source`` says which.
    """
    if poses not in POSE_CHOICES:
        raise ValueError(f"poses must be one of {', '.join(POSE_CHOICES)}, got {poses!r}")
    scene = _load_scene_given(Path(path), _skip_points)
    if _skip_points or poses == "given":
        return scene
    rec = read_refined_poses(scene.path, scene.frame_ids)
    if rec is None:
        if poses == "refined":
            raise SceneError(f"{scene.path}: no refined poses ({REFINED_POSES_FILE}); run `presim align "
                             f"{scene.path}` first or use the given poses")
        return scene
    scene.T_world_cam = rec[0]
    scene.poses_source = "refined"
    return scene


def save_refined_poses(path: str | Path, T_world_cam: np.ndarray, frame_ids: list[str], provenance: dict) -> Path:
    """Store refined camera poses beside a saved scene's given ones (which are never touched).

    One JSON file (``poses_refined.json``: frame ids, ``T_world_cam`` per frame at full float64
    precision, provenance), written atomically: an interrupted ``presim align`` leaves the scene as
    it was (no file, or the previous complete one).
    """
    path = Path(path)
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (len(frame_ids), 4, 4) or not np.all(np.isfinite(T)):
        raise SceneError(f"{path}: refined poses must be finite ({len(frame_ids)}, 4, 4), got {T.shape}")
    out = path / REFINED_POSES_FILE
    atomic_write_json(out, {"format": "presim-refined-poses", "version": 1, "frame_ids": list(frame_ids),
                            "T_world_cam": T.tolist(), "provenance": provenance}, indent=None)
    return out


def read_refined_poses(path: str | Path | None, frame_ids: list[str]) -> tuple[np.ndarray, dict] | None:
    """(T_world_cam (N, 4, 4), provenance) of ``poses_refined.json``, or None when the scene has none.
    A file whose frames differ from the scene's is an error (it belongs to another scene)."""
    if path is None:
        return None
    f = Path(path) / REFINED_POSES_FILE
    if not f.is_file():
        return None
    try:
        d = json.loads(f.read_text())
        T = np.asarray(d["T_world_cam"], dtype=np.float64)
        ids = list(d["frame_ids"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise SceneError(f"{f}: corrupt refined poses ({type(e).__name__}: {e}); delete it or rerun `presim align`") from None
    if ids != list(frame_ids) or T.shape != (len(frame_ids), 4, 4):
        raise SceneError(f"{f}: refined poses are for other frames ({len(ids)} frames) than the scene's "
                         f"({len(frame_ids)}); rerun `presim align --overwrite`")
    return T, dict(d.get("provenance", {}))


def _load_scene_given(path: Path, _skip_points: bool = False) -> Scene:
    hdr_path = path / "scene.json"
    if not hdr_path.is_file() and not _skip_points:  # save_scene reads its arrays before scene.json exists
        if path.with_name(path.name + ".partial").exists():
            raise SceneError(f"{path}: scene is incomplete (an interrupted save left {path.name}.partial)")
        raise SceneError(f"{path}: not a PreSim scene (no scene.json); import a capture with `presim import`")
    color = _load_array(path / "color.npy")
    depth = _load_array(path / "depth.npy")
    if _skip_points:
        n = color.shape[0]
        K = Intrinsics(1.0, 1.0, 0.0, 0.0, color.shape[2], color.shape[1])
        return Scene([str(i) for i in range(n)], np.zeros(n), np.tile(np.eye(4), (n, 1, 1)), [K] * n,
                     ArrayFrameSource(color, depth), SceneMeta("", ""))
    try:
        hdr = json.loads(hdr_path.read_text())
    except json.JSONDecodeError as e:
        raise SceneError(f"{hdr_path}: corrupt JSON ({e})") from e
    except UnicodeDecodeError as e:
        raise SceneError(f"{hdr_path}: not UTF-8 text ({e})") from None
    if not isinstance(hdr, dict):
        raise SceneError(f"{hdr_path}: the top level must be a JSON object, got a JSON {_json_kind(hdr)}")
    if hdr.get("format") != FORMAT_NAME:
        raise SceneError(f"{hdr_path}: unknown format {hdr.get('format')!r}")
    if hdr.get("version") != FORMAT_VERSION:
        raise SceneError(f"{hdr_path}: scene format version {hdr.get('version')} is not supported "
                         f"(this PreSim reads version {FORMAT_VERSION})")
    _check_header(hdr_path, hdr, color, depth)
    try:
        scene = _scene_from_header(path, hdr, color, depth)
    except SceneError:
        raise
    except (KeyError, TypeError, IndexError, ValueError) as e:
        raise SceneError(f"{hdr_path}: missing or malformed field ({type(e).__name__}: {e})") from None
    check_scene_geometry(scene.T_world_cam, scene.intrinsics, scene.frame_ids, str(hdr_path))
    return scene


def _json_kind(v) -> str:
    return {list: "list", str: "string", bool: "boolean", int: "number", float: "number",
            type(None): "null"}.get(type(v), type(v).__name__)


def _check_header(hdr_path: Path, hdr: dict, color: np.ndarray, depth: np.ndarray) -> None:
    """The top-level fields of scene.json, each refusal naming the field at fault."""
    for key in ("width", "height", "frames"):
        if key not in hdr:
            raise SceneError(f"{hdr_path}: missing or malformed field (KeyError: {key!r})")
    for key in ("width", "height"):
        v = hdr.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise SceneError(f"{hdr_path}: field {key!r} must be a whole number >= 1, got {v!r}")
    frames = hdr.get("frames")
    if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
        raise SceneError(f"{hdr_path}: field 'frames' must be a list of objects, got a JSON {_json_kind(frames)}")
    n = len(frames)
    if "num_frames" in hdr and hdr["num_frames"] != n:
        raise SceneError(f"{hdr_path}: field 'num_frames' is {hdr['num_frames']!r} but 'frames' lists {n}")
    if depth.shape != color.shape[:3]:
        raise SceneError(f"{hdr_path.parent}: color.npy {color.shape} and depth.npy {depth.shape} disagree")
    for axis, (key, want) in enumerate((("frames", n), ("height", hdr["height"]), ("width", hdr["width"]))):
        if color.shape[axis] != want:
            raise SceneError(f"{hdr_path}: field {key!r} says {want} but color.npy holds {color.shape[axis]} "
                             f"(arrays {color.shape})")
    for key in ("objects",):
        if key in hdr and not isinstance(hdr[key], list):
            raise SceneError(f"{hdr_path}: field {key!r} must be a list, got a JSON {_json_kind(hdr[key])}")
    for key in ("meta", "floor"):
        if hdr.get(key) is not None and not isinstance(hdr[key], dict):
            raise SceneError(f"{hdr_path}: field {key!r} must be an object, got a JSON {_json_kind(hdr[key])}")


def _scene_from_header(path: Path, hdr: dict, color: np.ndarray, depth: np.ndarray) -> Scene:
    frames = hdr["frames"]
    n = len(frames)
    refined = None
    if (path / "depth_refined.npy").is_file():
        refined = _load_array(path / "depth_refined.npy")
        if refined.shape != depth.shape:
            raise SceneError(f"{path / 'depth_refined.npy'}: shape {refined.shape} != depth {depth.shape}")
    fused = None
    if (path / "depth_fused.npy").is_file():
        fused = _load_array(path / "depth_fused.npy")
        if fused.shape != depth.shape:
            raise SceneError(f"{path / 'depth_fused.npy'}: shape {fused.shape} != depth {depth.shape}")
    completed = None
    if (path / "depth_completed.npy").is_file():
        completed = _load_array(path / "depth_completed.npy")
        if completed.shape != depth.shape or completed.dtype != np.float32:
            raise SceneError(f"{path / 'depth_completed.npy'}: {completed.dtype} {completed.shape}, expected float32 "
                             f"{depth.shape} like depth.npy (recompute it: presim complete --overwrite)")
    points = PointCloud(_load_array(path / "points_xyz.npy", mmap=False), _load_array(path / "points_rgb.npy", mmap=False))
    fl = hdr.get("floor")
    floor = None if fl is None else FloorPlane(tuple(fl["normal"]), fl["offset"], fl.get("inlier_frac", 0.0))
    objects = [
        SceneObject(o["obj_id"], o["name"], np.asarray(o["T_world_obj"], dtype=np.float64),
                    o.get("model_path"), o.get("symmetric", False),
                    tuple(map(float, o["symmetry_axis"])) if o.get("symmetry_axis") else None)
        for o in hdr.get("objects", [])
    ]
    return Scene(
        frame_ids=[f["frame_id"] for f in frames],
        stamps_s=np.array([f["stamp_s"] for f in frames], dtype=np.float64),
        T_world_cam=np.array([f["T_world_cam"] for f in frames], dtype=np.float64).reshape(n, 4, 4),
        intrinsics=[Intrinsics.from_dict(f["intrinsics"]) for f in frames],
        frames=ArrayFrameSource(color, depth),
        meta=SceneMeta.from_dict(hdr["meta"]),
        points=points,
        floor=floor,
        gravity_world=np.asarray(hdr.get("gravity_world", [0, 0, -1]), dtype=np.float64),
        objects=objects,
        depth_refined=refined,
        depth_fused=fused,
        depth_completed=completed,
        path=path,
        photometric=_load_photometric(path),
        render_filter_sigma_px=_load_render_filter(path),
    )


def model_abspath(scene: Scene, obj: SceneObject) -> Path | None:
    """Absolute path of an object's model file."""
    if obj.model_path is None:
        return None
    p = Path(obj.model_path)
    return p if p.is_absolute() or scene.path is None else scene.path / p


def unmap_pages(arr: np.ndarray) -> None:
    """Drop this process's mapping of the pages of ``arr`` when it is a slice of a read-only memory map
    (a saved scene's colour/depth arrays): the prepared view holds copies, so the pages would only sit
    in the process's RSS (they stay in the page cache). No-op otherwise."""
    mm, b = None, arr
    while b is not None and mm is None:  # np.asarray(memmap[i]) is a plain view: find the map below
        mm, b = getattr(b, "_mmap", None), getattr(b, "base", None)
    if mm is None or arr.flags.writeable or not hasattr(mmap, "MADV_DONTNEED") or arr.nbytes == 0:
        return
    try:
        start = arr.ctypes.data - np.frombuffer(mm, np.uint8).ctypes.data
        lo = start // mmap.PAGESIZE * mmap.PAGESIZE
        hi = min(len(mm), -(-(start + arr.nbytes) // mmap.PAGESIZE) * mmap.PAGESIZE)
        if 0 <= lo < hi:
            mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
    except (ValueError, OSError, TypeError):  # closed map, unusual layout: keep the pages
        pass
