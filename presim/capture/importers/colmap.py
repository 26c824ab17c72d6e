"""COLMAP sparse model (text or binary) + a folder of metric depth maps.

Layout (the model folder is the first of ``sparse/0``, ``sparse``, ``.`` that holds a model)::

    SRC/images/<NAME>                     the registered images (NAME as in images.txt/.bin)
    SRC/sparse/0/cameras.txt|bin          CAMERA_ID MODEL WIDTH HEIGHT PARAMS
    SRC/sparse/0/images.txt|bin           IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME  (+ a points line)
    SRC/sparse/0/points3D.txt|bin         optional; read and counted (the scene cloud is fused from depth)
    SRC/depths/<NAME stem>.npy            float metres (NaN/inf/<=0 -> invalid), or
    SRC/depths/<NAME stem>.png            uint16 millimetres, 0 = invalid        (also depth/)

Traps handled at this border:
- COLMAP poses are world-to-camera (``x_cam = R(q) x_world + t``, q scalar-first): inverted here.
- COLMAP puts pixel (0, 0) at the *corner* of the top-left pixel; PreSim at its centre:
  ``cx = cx_colmap - 0.5``, ``cy = cy_colmap - 0.5``.
- A COLMAP reconstruction has an arbitrary scale unless it was made metric; the depth maps must be in
  the same (metric) frame as the poses. COLMAP's own dense ``stereo/depth_maps/*.bin`` are not read.
- Camera models: SIMPLE_PINHOLE, PINHOLE, OPENCV (color undistorted with bilinear, depth with nearest
  interpolation, into the same K); any other model is an error naming it.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, Undistortion, checked_pose, decode_depth_png_scale, image_size_wh, read_depth_camera,
    require_file, select_indices,
)
from presim.capture.scene import PointCloud, Scene, SceneError, SceneMeta
from presim.geometry import Intrinsics, invert, make_pose, quat_xyzw_to_R

NAME = "colmap"
VERSION = "1"

# id -> (name, number of params), from colmap/src/colmap/sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_NPARAMS = {name: n for name, n in CAMERA_MODELS.values()}
SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "OPENCV")
DEPTH_DIRS = ("depths", "depth")


def find_model_dir(src: Path) -> Path | None:
    for d in (src / "sparse" / "0", src / "sparse", src):
        for ext in (".txt", ".bin"):
            if (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file():
                return d
    return None


def detect(src: Path) -> bool:
    return src.is_dir() and find_model_dir(src) is not None


# ---- text -------------------------------------------------------------------------------------
def _data_lines(path: Path) -> list[tuple[int, str]]:
    require_file(path)
    return [(i, l.strip()) for i, l in enumerate(path.read_text(errors="replace").splitlines(), 1)
            if l.strip() and not l.lstrip().startswith("#")]


def read_cameras_text(path: Path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    cams = {}
    for line_no, s in _data_lines(path):
        p = s.split()
        try:
            cid, model, w, h = int(p[0]), p[1], int(p[2]), int(p[3])
            params = np.array([float(x) for x in p[4:]])
        except (ValueError, IndexError):
            raise SceneError(f"{path}:{line_no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]': {s!r}") from None
        if model in _NPARAMS and len(params) != _NPARAMS[model]:
            raise SceneError(f"{path}:{line_no}: {model} needs {_NPARAMS[model]} params, got {len(params)}")
        cams[cid] = (model, w, h, params)
    return cams


def read_images_text(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    """(image_id, q_wxyz, t, camera_id, name) per image; every image has a 2nd (points) line."""
    require_file(path)
    lines = path.read_text(errors="replace").splitlines()
    out = []
    k = 0
    while k < len(lines):
        s = lines[k].strip()
        if not s or s.startswith("#"):
            k += 1
            continue
        p = s.split()
        try:
            iid = int(p[0])
            q = np.array([float(x) for x in p[1:5]])
            t = np.array([float(x) for x in p[5:8]])
            cid = int(p[8])
            name = " ".join(p[9:])
            if not name:
                raise ValueError
        except (ValueError, IndexError):
            raise SceneError(f"{path}:{k + 1}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME': {s!r}") from None
        out.append((iid, q, t, cid, name))
        k += 2  # skip the POINTS2D line (may be empty)
    return out


def read_points_text(path: Path) -> PointCloud:
    xyz, rgb = [], []
    for line_no, s in _data_lines(path):
        p = s.split()
        try:
            xyz.append([float(x) for x in p[1:4]])
            rgb.append([int(x) for x in p[4:7]])
        except (ValueError, IndexError):
            raise SceneError(f"{path}:{line_no}: expected 'POINT3D_ID X Y Z R G B ...': {s!r}") from None
    return PointCloud(np.asarray(xyz, np.float32).reshape(-1, 3), np.asarray(rgb, np.uint8).reshape(-1, 3))


# ---- binary -----------------------------------------------------------------------------------
class _Reader:
    def __init__(self, path: Path):
        require_file(path)
        self.path, self.buf, self.pos = path, path.read_bytes(), 0

    def read(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.buf):
            raise SceneError(f"{self.path}: truncated binary file (needed {size} bytes at offset {self.pos})")
        vals = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return vals

    def cstring(self) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise SceneError(f"{self.path}: truncated binary file (unterminated image name)")
        s = self.buf[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s


def read_cameras_binary(path: Path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    r = _Reader(path)
    (n,) = r.read("<Q")
    cams = {}
    for _ in range(n):
        cid, mid, w, h = r.read("<iiQQ")
        if mid not in CAMERA_MODELS:
            raise SceneError(f"{path}: unknown camera model id {mid}")
        model, npar = CAMERA_MODELS[mid]
        cams[cid] = (model, int(w), int(h), np.array(r.read(f"<{npar}d")))
    return cams


def read_images_binary(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    r = _Reader(path)
    (n,) = r.read("<Q")
    out = []
    for _ in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.read("<idddddddi")
        name = r.cstring()
        (npts,) = r.read("<Q")
        r.pos += npts * 24  # (x, y double; point3D_id int64) per 2D point, not needed
        if r.pos > len(r.buf):
            raise SceneError(f"{path}: truncated binary file (points of image {iid})")
        out.append((iid, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cid, name))
    return out


def read_points_binary(path: Path) -> PointCloud:
    r = _Reader(path)
    (n,) = r.read("<Q")
    xyz = np.empty((n, 3), np.float32)
    rgb = np.empty((n, 3), np.uint8)
    for k in range(n):
        _, x, y, z, cr, cg, cb, _, tl = r.read("<QdddBBBdQ")
        xyz[k] = (x, y, z)
        rgb[k] = (cr, cg, cb)
        r.pos += 8 * tl  # track (image_id int32, point2D_idx int32)
    return PointCloud(xyz, rgb)


# ---- scene ------------------------------------------------------------------------------------
def camera_intrinsics(model: str, w: int, h: int, params: np.ndarray, where: str) -> tuple[Intrinsics, Undistortion | None]:
    """PreSim intrinsics (pixel-centre origin) and the undistortion to apply, for one COLMAP camera."""
    if model not in SUPPORTED:
        raise SceneError(f"{where}: camera model {model} is not supported (supported: {', '.join(SUPPORTED)}); "
                         "undistort the images with `colmap image_undistorter` first")
    p = params
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    else:
        fx, fy, cx, cy = p[:4]
    # COLMAP's pixel origin is the top-left corner; ours the centre of the top-left pixel.
    K = Intrinsics(fx, fy, cx - 0.5, cy - 0.5, w, h)
    if model == "OPENCV" and np.any(p[4:8] != 0):
        return K, Undistortion(K, tuple(float(x) for x in p[4:8]), K)
    return K, None


def find_depth(src: Path, name: str) -> Path:
    stem = str(Path(name).with_suffix(""))
    for d in DEPTH_DIRS:
        for cand in (f"{stem}.npy", f"{stem}.png", f"{name}.npy", f"{name}.png"):
            if (src / d / cand).is_file():
                return src / d / cand
    raise SceneError(f"{src}: no depth map for image {name} (expected {DEPTH_DIRS[0]}/{stem}.npy "
                     f"(float metres) or {DEPTH_DIRS[0]}/{stem}.png (uint16 mm))")


def _decode_depth(raw: np.ndarray, path: Path) -> np.ndarray:
    if path.suffix.lower() == ".npy":
        if not np.issubdtype(raw.dtype, np.floating):
            raise SceneError(f"{path}: .npy depth must be float metres, got {raw.dtype}")
        return raw.astype(np.float32)
    return decode_depth_png_scale(1e-3)(raw, path)


def read(src: Path, every: int = 1, max_frames: int | None = None) -> Scene:
    src = Path(src)
    mdir = find_model_dir(src)
    if mdir is None:
        raise SceneError(f"{src}: no COLMAP model (cameras.txt|bin + images.txt|bin in sparse/0, sparse or the folder)")
    binary = not (mdir / "cameras.txt").is_file()
    if binary:
        cams = read_cameras_binary(mdir / "cameras.bin")
        images = read_images_binary(mdir / "images.bin")
        pts_path = mdir / "points3D.bin"
        points = read_points_binary(pts_path) if pts_path.is_file() else None
    else:
        cams = read_cameras_text(mdir / "cameras.txt")
        images = read_images_text(mdir / "images.txt")
        pts_path = mdir / "points3D.txt"
        points = read_points_text(pts_path) if pts_path.is_file() else None
    if points is not None and len(points) == 0:
        points = None
    img_file = mdir / ("images.bin" if binary else "images.txt")
    if not images:
        raise SceneError(f"{img_file}: no registered images")
    images.sort(key=lambda im: im[4])  # capture order = file name order (COLMAP ids are arbitrary)
    images = [images[i] for i in select_indices(len(images), every, max_frames)]
    cam_file = mdir / ("cameras.bin" if binary else "cameras.txt")
    cam_cache: dict[int, tuple[Intrinsics, Undistortion | None]] = {}
    ids, poses, Ks, undists, colors, depths = [], [], [], [], [], []
    for iid, q_wxyz, t, cid, name in images:
        if cid not in cams:
            raise SceneError(f"{img_file}: image {name} uses camera {cid}, not in {cam_file}")
        if cid not in cam_cache:
            cam_cache[cid] = camera_intrinsics(*cams[cid], where=f"{cam_file} camera {cid}")
        K, ud = cam_cache[cid]
        if not (np.all(np.isfinite(q_wxyz)) and np.all(np.isfinite(t))):
            raise SceneError(f"{img_file}: image {name}: non-finite pose")
        if np.linalg.norm(q_wxyz) < 1e-6:
            raise SceneError(f"{img_file}: image {name}: zero quaternion")
        # COLMAP stores world-to-camera with a scalar-first quaternion.
        T_cam_world = make_pose(quat_xyzw_to_R(np.r_[q_wxyz[1:], q_wxyz[0]]), t)
        poses.append(checked_pose(invert(T_cam_world), f"{img_file}: image {name}"))
        cpath = require_file(src / "images" / name, "image")
        wh = image_size_wh(cpath)
        if wh != (K.width, K.height):
            raise SceneError(f"{cpath}: resolution {wh[0]}x{wh[1]} != camera {cid} ({K.width}x{K.height})")
        ids.append(name)
        Ks.append(K)
        undists.append(ud)
        colors.append(cpath)
        depths.append(find_depth(src, name))
    depth_cam = read_depth_camera(src, depths[0])
    source = FileFrameSource(colors, depths, Ks, _decode_depth, undistortion=undists, depth_camera=depth_cam)
    notes = [f"COLMAP {'binary' if binary else 'text'} model {mdir}; stamps = index / 30 s",
             "cx, cy shifted by -0.5 px (COLMAP pixel origin is the pixel corner)"]
    if depth_cam is not None:
        notes.append("depth registered into the color camera at read (depth-intrinsics.txt + depth-to-color.txt)")
    if any(u is not None for u in undists):
        notes.append("OPENCV distortion removed at read (color bilinear, depth nearest)")
    if points is not None:
        # The scene's cloud is fused from the depth maps like every other format (dense, colored);
        # the sparse SfM points are only counted.
        notes.append(f"{len(points)} sparse COLMAP points in {pts_path.name} (not used as the scene cloud)")
    return Scene(ids, np.arange(len(ids)) / 30.0, np.stack(poses), Ks, source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=tuple(notes)))
