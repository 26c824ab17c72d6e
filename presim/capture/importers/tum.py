"""TUM RGB-D benchmark sequences.

Files::

    rgb.txt           '# ...' comments, then '<stamp_s> rgb/<stamp>.png'
    depth.txt         '<stamp_s> depth/<stamp>.png'  (uint16, 1/5000 m per unit, 0 = invalid,
                      already registered to the color camera by the TUM tools)
    groundtruth.txt   '<stamp_s> tx ty tz qx qy qz qw': pose of the color camera's optical centre in the
                      mocap world = T_world_cam (OpenCV camera), metres
    intrinsics        camera-intrinsics.txt / intrinsics.K.txt (3x3) or calibration.txt
                      ('fx fy cx cy [k1 k2 p1 p2 k3]'); otherwise the published Freiburg 1/2/3 values are
                      used when the folder name says which sensor (fr1/fr2 with their distortion);
                      distorted images are undistorted and cropped to the valid rectangle at the
                      same size (adjusted intrinsics, no black borders: valid_rectangle_intrinsics)

Association (as TUM's ``associate.py``): every rgb/depth pair within ``max_dt_s`` (0.02 s), taken
greedily by smallest stamp difference, one-to-one. Ground truth is interpolated at the rgb stamp
(linear position, slerp rotation) between the two bracketing mocap samples when they are at most
``max_gt_gap_s`` apart; frames outside the ground truth's time range or in a mocap gap are dropped
(the number dropped is written to the scene's notes).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, Undistortion, check_sizes, checked_pose, decode_depth_png_scale, image_size_wh,
    read_depth_camera, read_matrix_txt, require_file, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta
from presim.formats.tum import interpolate_pose, read_tum_rows
from presim.geometry import Intrinsics

NAME = "tum"
VERSION = "1"
DEPTH_SCALE_M = 1.0 / 5000.0
MAX_DT_S = 0.02
MAX_GT_GAP_S = 0.1

# Published calibration (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats), OpenCV
# convention: fx fy cx cy, k1 k2 p1 p2 k3. Freiburg 3 images are distributed undistorted.
FREIBURG = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), None),
}


def detect(src: Path) -> bool:
    return src.is_dir() and (src / "rgb.txt").is_file() and (src / "depth.txt").is_file()


def read_list(path: Path, ncols: int) -> list[tuple[float, list[str]]]:
    """Lines '<stamp> <ncols-1 fields>' of a TUM text file, comments skipped, sorted by stamp."""
    require_file(path)
    out = []
    for line_no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.replace(",", " ").strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != ncols:
            raise SceneError(f"{path}:{line_no}: expected {ncols} fields, got {len(parts)}: {line!r}")
        try:
            stamp = float(parts[0])
        except ValueError:
            raise SceneError(f"{path}:{line_no}: bad timestamp {parts[0]!r}") from None
        if not np.isfinite(stamp):
            raise SceneError(f"{path}:{line_no}: non-finite timestamp")
        out.append((stamp, parts[1:]))
    out.sort(key=lambda t: t[0])
    return out


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt_s: float = MAX_DT_S) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) with |a_i - b_j| <= max_dt_s, greedily by smallest difference; sorted by i."""
    a, b = np.asarray(stamps_a, float), np.asarray(stamps_b, float)
    cands = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(b, t - max_dt_s), np.searchsorted(b, t + max_dt_s, side="right")
        cands.extend((abs(t - b[j]), i, j) for j in range(lo, hi))
    cands.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def valid_rectangle_intrinsics(K: Intrinsics, dist: tuple[float, ...]) -> Intrinsics:
    """Intrinsics of the undistorted image, same size, that holds only pixels with data.

    Undistorting a Freiburg 1 frame into its own K leaves 5.3 % of the image as black corners with
    no color and no depth, which every render and the evaluation would score. We crop instead: the
    output camera zooms in (fx 517 -> 547 for fr1) so that every output pixel maps inside the raw
    image (OpenCV's optimal new camera matrix with alpha = 0), at the same resolution.
    """
    K_new, _ = cv2.getOptimalNewCameraMatrix(K.K, np.asarray(dist, np.float64), K.size_wh, 0.0, K.size_wh)
    return Intrinsics(float(K_new[0, 0]), float(K_new[1, 1]), float(K_new[0, 2]), float(K_new[1, 2]), K.width, K.height)


def read_intrinsics(src: Path, w: int, h: int) -> tuple[Intrinsics, Undistortion | None, str]:
    for name in ("camera-intrinsics.txt", "intrinsics.K.txt"):
        if (src / name).is_file():
            return Intrinsics.from_K(read_matrix_txt(src / name, (3, 3)), w, h, source=str(src / name)), None, name
    calib = src / "calibration.txt"
    if calib.is_file():
        try:
            vals = [float(x) for x in calib.read_text().split()]
        except ValueError:
            raise SceneError(f"{calib}: expected 'fx fy cx cy [k1 k2 p1 p2 k3]'") from None
        if len(vals) not in (4, 8, 9):
            raise SceneError(f"{calib}: expected 4, 8 or 9 numbers (fx fy cx cy [k1 k2 p1 p2 k3]), got {len(vals)}")
        K = Intrinsics(*vals[:4], w, h)
        dist = tuple(vals[4:])
        if dist and any(dist):
            K_out = valid_rectangle_intrinsics(K, dist)
            return K_out, Undistortion(K, dist, K_out), "calibration.txt (undistorted to the valid rectangle)"
        return K, None, "calibration.txt"
    m = re.search(r"freiburg([123])", str(src.resolve()))
    if m:
        key = f"freiburg{m.group(1)}"
        (fx, fy, cx, cy), dist = FREIBURG[key]
        K = Intrinsics(fx, fy, cx, cy, w, h)
        if dist:
            K_out = valid_rectangle_intrinsics(K, dist)
            return K_out, Undistortion(K, dist, K_out), f"published {key} calibration (undistorted to the valid rectangle)"
        return K, None, f"published {key} calibration"
    raise SceneError(f"{src}: no intrinsics (add camera-intrinsics.txt with the 3x3 K, or calibration.txt "
                     "'fx fy cx cy [k1 k2 p1 p2 k3]'; Freiburg folders are recognised by name)")


def _read_without_poses(src: Path, rgb, dep, every: int, max_frames: int | None, max_dt_s: float) -> Scene:
    """A TUM folder without groundtruth.txt: frames with placeholder poses (``poses_source="none"``);
    ``import_capture`` estimates them."""
    if not rgb or not dep:
        raise SceneError(f"{src}: empty {'rgb.txt' if not rgb else 'depth.txt'}")
    pairs = associate(np.array([t for t, _ in rgb]), np.array([t for t, _ in dep]), max_dt_s)
    if not pairs:
        raise SceneError(f"{src}: no rgb/depth pair within {max_dt_s} s")
    pairs = [pairs[k] for k in select_indices(len(pairs), every, max_frames)]
    colors = [src / rgb[i][1][0] for i, _ in pairs]
    depths = [src / dep[j][1][0] for _, j in pairs]
    for p in colors + depths:
        require_file(p, "image")
    w, h = image_size_wh(colors[0])
    K, undist, k_src = read_intrinsics(src, w, h)
    check_sizes(colors, (w, h), "color")
    check_sizes(depths, (w, h), "depth")
    stamps = np.array([rgb[i][0] for i, _ in pairs])
    ids = [f"{t:.6f}" for t in stamps]
    notes = (f"intrinsics: {k_src}", "no groundtruth.txt: poses estimated at import")
    source = FileFrameSource(colors, depths, K, decode_depth_png_scale(DEPTH_SCALE_M), undistortion=undist)
    return Scene(ids, stamps, np.tile(np.eye(4), (len(ids), 1, 1)), [K] * len(ids), source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=notes), poses_source="none")


def read(src: Path, every: int = 1, max_frames: int | None = None, max_dt_s: float = MAX_DT_S,
         max_gt_gap_s: float = MAX_GT_GAP_S) -> Scene:
    src = Path(src)
    rgb = read_list(src / "rgb.txt", 2)
    dep = read_list(src / "depth.txt", 2)
    gt_path = src / "groundtruth.txt"
    if not gt_path.is_file():
        return _read_without_poses(src, rgb, dep, every, max_frames, max_dt_s)
    if not rgb or not dep:
        empty = [p for p, l in (("rgb.txt", rgb), ("depth.txt", dep)) if not l]
        raise SceneError(f"{src}: empty {', '.join(empty)}")
    try:
        gt_stamps, gt_vals = read_tum_rows(gt_path)  # the one TUM trajectory reader (file:line errors)
    except ValueError as e:
        raise SceneError(str(e)) from None
    pairs = associate(np.array([t for t, _ in rgb]), np.array([t for t, _ in dep]), max_dt_s)
    if not pairs:
        raise SceneError(f"{src}: no rgb/depth pair within {max_dt_s} s")
    frames = []
    dropped = 0
    for i, j in pairs:
        T = interpolate_pose(gt_stamps, gt_vals, rgb[i][0], max_gt_gap_s)
        if T is None:
            dropped += 1
            continue
        frames.append((rgb[i][0], src / rgb[i][1][0], src / dep[j][1][0], T))
    if not frames:
        raise SceneError(f"{gt_path}: no rgb stamp inside the ground truth's time range")
    frames = [frames[k] for k in select_indices(len(frames), every, max_frames)]
    colors = [f[1] for f in frames]
    depths = [f[2] for f in frames]
    for p in colors + depths:
        require_file(p, "image")
    w, h = image_size_wh(colors[0])
    K, undist, k_src = read_intrinsics(src, w, h)
    check_sizes(colors, (w, h), "color")
    depth_cam = read_depth_camera(src, depths[0])
    check_sizes(depths, depth_cam.K.size_wh if depth_cam else (w, h), "depth")
    poses = np.stack([checked_pose(f[3], f"{gt_path} at stamp {f[0]:.6f}") for f in frames])
    ids = [f"{f[0]:.6f}" for f in frames]
    if len(set(ids)) != len(ids):
        raise SceneError(f"{src / 'rgb.txt'}: duplicate rgb stamps")
    notes = [f"intrinsics: {k_src}", f"rgb/depth associated within {max_dt_s} s; ground truth interpolated"]
    if dropped:
        notes.append(f"{dropped} rgb frames dropped: outside ground truth range or mocap gap > {max_gt_gap_s} s")
    if depth_cam is not None:
        notes.append("depth registered into the color camera at read (depth-intrinsics.txt + depth-to-color.txt)")
    source = FileFrameSource(colors, depths, K, decode_depth_png_scale(DEPTH_SCALE_M), undistortion=undist,
                             depth_camera=depth_cam)
    return Scene(ids, np.array([f[0] for f in frames]), poses, [K] * len(ids), source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=tuple(notes)))
