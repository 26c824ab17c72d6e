"""KinectFusion / 7-Scenes folder layout (also what ``presim drive --record`` writes).

Files::

    frame-XXXXXX.color.png|jpg   RGB
    frame-XXXXXX.depth.png       uint16 millimetres, registered to color; 0 and 65535 = invalid
    frame-XXXXXX.pose.txt        4x4 camera-to-world (T_world_cam, OpenCV camera), metres
    camera-intrinsics.txt | intrinsics.K.txt   3x3 K of the color camera
    timestamps.txt               optional, lines "frame-XXXXXX <stamp_s>"; else stamp = number / 30 s

The frame number in the name (``frame-000015`` -> 15) orders the frames and gives the default stamp
(30 Hz), so a sequence stored every other frame keeps its real timing.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    FileFrameSource, check_sizes, checked_pose, decode_depth_png_scale, image_size_wh, read_depth_camera,
    read_matrix_txt, require_file, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta
from presim.geometry import Intrinsics

NAME = "kinfu"
VERSION = "1"
INTRINSICS_FILES = ("camera-intrinsics.txt", "intrinsics.K.txt")
_COLOR_RE = re.compile(r"^(frame-(\d+))\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
DEFAULT_RATE_HZ = 30.0


def detect(src: Path) -> bool:
    """A folder with ``frame-*.color.*`` and ``frame-*.pose.txt`` files, or (no poses: estimated at
    import) ``frame-*.color.*`` + ``frame-*.depth.png`` + an intrinsics file (:data:`INTRINSICS_FILES`)."""
    if not (src.is_dir() and any(src.glob("frame-*.color.*"))):
        return False
    return any(src.glob("frame-*.pose.txt")) or (any(src.glob("frame-*.depth.png"))
                                                  and any((src / f).is_file() for f in INTRINSICS_FILES))


def list_frames(src: Path) -> list[tuple[str, int, Path]]:
    """``(frame_id, number, color_path)`` sorted by number."""
    out = []
    for p in src.iterdir():
        m = _COLOR_RE.match(p.name)
        if m:
            out.append((m.group(1), int(m.group(2)), p))
    out.sort(key=lambda t: t[1])
    ids = [t[0] for t in out]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise SceneError(f"{src}: frames with both a .png and a .jpg color image: {dup[:5]}")
    return out


def read_intrinsics_K(src: Path) -> np.ndarray:
    for name in INTRINSICS_FILES:
        if (src / name).is_file():
            K = read_matrix_txt(src / name, (3, 3))
            if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise SceneError(f"{src / name}: invalid camera matrix {K.tolist()}")
            return K
    raise SceneError(f"{src}: no intrinsics file (expected one of {', '.join(INTRINSICS_FILES)})")


def read_timestamps(path: Path) -> dict[str, float]:
    stamps: dict[str, float] = {}
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) != 2:
                raise ValueError
            stamps[parts[0]] = float(parts[1])
        except ValueError:
            raise SceneError(f"{path}:{line_no}: expected 'frame-XXXXXX <stamp_s>', got {line!r}") from None
        if not np.isfinite(stamps[parts[0]]):
            raise SceneError(f"{path}:{line_no}: non-finite stamp")
    return stamps


def read(src: Path, every: int = 1, max_frames: int | None = None) -> Scene:
    src = Path(src)
    frames = list_frames(src)
    if not frames:
        raise SceneError(f"{src}: no frame-XXXXXX.color.png/jpg files")
    frames = [frames[i] for i in select_indices(len(frames), every, max_frames)]
    K_mat = read_intrinsics_K(src)
    w, h = image_size_wh(frames[0][2])
    K = Intrinsics.from_K(K_mat, w, h, source=f"{src} (intrinsics vs {frames[0][2].name})")
    stamps_file = src / "timestamps.txt"
    stamp_map = read_timestamps(stamps_file) if stamps_file.is_file() else None

    ids, stamps, poses, colors, depths = [], [], [], [], []
    has_poses = any(src.glob("frame-*.pose.txt"))  # none at all: estimated by import_capture
    for fid, num, cpath in frames:
        dpath = require_file(src / f"{fid}.depth.png", "depth image")
        if has_poses:
            ppath = require_file(src / f"{fid}.pose.txt", "pose file")
            poses.append(checked_pose(read_matrix_txt(ppath, (4, 4)), str(ppath)))
        else:
            poses.append(np.eye(4))
        if stamp_map is not None:
            if fid not in stamp_map:
                raise SceneError(f"{stamps_file}: no stamp for {fid}")
            stamps.append(stamp_map[fid])
        else:
            stamps.append(num / DEFAULT_RATE_HZ)
        ids.append(fid)
        colors.append(cpath)
        depths.append(dpath)
    check_sizes(colors, (w, h), "color")
    depth_cam = read_depth_camera(src, depths[0])
    check_sizes(depths, depth_cam.K.size_wh if depth_cam else (w, h), "depth")
    # 65535 is the "no return / saturated" code of Kinect-style 16-bit depth.
    source = FileFrameSource(colors, depths, K, decode_depth_png_scale(1e-3, invalid_codes=(0, 65535)),
                             depth_camera=depth_cam)
    notes = () if stamp_map is not None else (f"stamps = frame number / {DEFAULT_RATE_HZ:g} Hz (no timestamps.txt)",)
    if depth_cam is not None:
        notes += ("depth registered into the color camera at read (depth-intrinsics.txt + depth-to-color.txt)",)
    if not has_poses:
        notes += ("no frame-*.pose.txt: poses estimated at import",)
    return Scene(ids, np.asarray(stamps), np.stack(poses), [K] * len(ids), source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=notes),
                 poses_source="given" if has_poses else "none")
