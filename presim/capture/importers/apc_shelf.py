"""MIT-Princeton APC 2016 "Shelf & Tote" scene folders (apc-vision-toolbox layout).

Files::

    cam.info.txt               '# <title>' lines each followed by a matrix: color K, depth K,
                               depth-to-color extrinsic, bin-to-world, and one
                               'Camera-to-world extrinsic matrix (camera pose) for frame-XXXXXX' per frame
    frame-XXXXXX.color.png     RGB 640x480
    frame-XXXXXX.depth.png     uint16, REGISTERED to color, circularly bit-rotated right by 3 bits:
                               v = ((raw << 13) | (raw >> 3)) & 0xFFFF; depth_m = v / 10000
    raw/frame-XXXXXX.depth.png same encoding, unregistered (depth camera); used with ``raw_depth=True``
                               and registered into the color camera with depth K + extrinsic

There are no timestamps (the arm stops at each view): stamp = frame number / 30 s, noted in the meta.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from presim.capture.importers.common import (
    DepthCamera, FileFrameSource, check_sizes, checked_pose, image_size_wh, require_file, select_indices,
)
from presim.capture.scene import Scene, SceneError, SceneMeta
from presim.geometry import Intrinsics

NAME = "apc_shelf"
VERSION = "1"
_POSE_RE = re.compile(r"camera pose\)?\s*for\s+(frame-\d+)", re.IGNORECASE)


def detect(src: Path) -> bool:
    return src.is_dir() and (src / "cam.info.txt").is_file()


def decode_apc_depth(raw: np.ndarray, path: Path) -> np.ndarray:
    """Undo the toolbox's 3-bit circular shift; 1/10000 m units; 0 = invalid."""
    if raw.dtype != np.uint16:
        raise SceneError(f"{path}: APC depth must be uint16, got {raw.dtype}")
    r = raw.astype(np.uint32)
    v = ((r << 13) | (r >> 3)) & 0xFFFF
    return (v.astype(np.float32) / np.float32(10000.0))


def parse_cam_info(path: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """Sections of ``cam.info.txt``: title -> matrix; plus the comment lines without a matrix."""
    require_file(path, "cam.info.txt")
    sections: dict[str, list[list[float]]] = {}
    texts: list[str] = []
    title = None
    for line_no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            title = s.lstrip("#").strip()
            if ":" in title and not title.lower().startswith(("color", "depth", "camera", "bin")):
                texts.append(title)
                title = None
            continue
        if title is None:
            raise SceneError(f"{path}:{line_no}: numbers outside a '# ...' section: {s!r}")
        try:
            sections.setdefault(title, []).append([float(x) for x in s.split()])
        except ValueError:
            raise SceneError(f"{path}:{line_no}: not a row of numbers: {s!r}") from None
    out = {}
    for k, rows in sections.items():
        if len({len(r) for r in rows}) != 1:
            raise SceneError(f"{path}: section '{k}' has rows of different lengths")
        out[k] = np.asarray(rows, dtype=np.float64)
    return out, texts


def _section(sections: dict[str, np.ndarray], path: Path, prefix: str, shape) -> np.ndarray:
    for k, v in sections.items():
        if k.lower().startswith(prefix.lower()):
            if v.shape != shape:
                raise SceneError(f"{path}: section '{k}' must be {shape[0]}x{shape[1]}, got {v.shape}")
            return v
    raise SceneError(f"{path}: missing section '# {prefix} ...'")


def read(src: Path, every: int = 1, max_frames: int | None = None, raw_depth: bool = False) -> Scene:
    """Read an APC shelf scene; ``raw_depth=True`` registers ``raw/`` depth instead of using the
    toolbox's registered depth."""
    src = Path(src)
    info = src / "cam.info.txt"
    sections, texts = parse_cam_info(info)
    K_color = _section(sections, info, "Color camera intrinsic", (3, 3))
    poses: dict[str, np.ndarray] = {}
    for k, v in sections.items():
        m = _POSE_RE.search(k)
        if m:
            if v.shape != (4, 4):
                raise SceneError(f"{info}: pose of {m.group(1)} must be 4x4, got {v.shape}")
            poses[m.group(1)] = checked_pose(v, f"{info}: pose of {m.group(1)}")
    if not poses:
        raise SceneError(f"{info}: no 'Camera-to-world extrinsic matrix (camera pose) for frame-XXXXXX' section")
    ids = sorted(poses, key=lambda f: int(f.split("-")[1]))
    ids = [ids[i] for i in select_indices(len(ids), every, max_frames)]
    colors = [require_file(src / f"{f}.color.png", "color image") for f in ids]
    depth_dir = src / "raw" if raw_depth else src
    depths = [require_file(depth_dir / f"{f}.depth.png", "depth image") for f in ids]
    w, h = image_size_wh(colors[0])
    K = Intrinsics.from_K(K_color, w, h, source=f"{src} (cam.info.txt vs {colors[0].name})")
    check_sizes(colors, (w, h), "color")
    depth_cam = None
    if raw_depth:
        K_d = _section(sections, info, "Depth camera intrinsic", (3, 3))
        T_cd = checked_pose(_section(sections, info, "Depth-to-color camera extrinsic", (4, 4)),
                            f"{info}: depth-to-color extrinsic")
        dw, dh = image_size_wh(depths[0])
        depth_cam = DepthCamera(Intrinsics.from_K(K_d, dw, dh), T_cd)
        check_sizes(depths, (dw, dh), "raw depth")
    else:
        check_sizes(depths, (w, h), "depth")
    source = FileFrameSource(colors, depths, K, decode_apc_depth, depth_camera=depth_cam)
    stamps = np.array([int(f.split("-")[1]) / 30.0 for f in ids])
    notes = tuple(texts) + ("no timestamps in the APC format: stamp = frame number / 30 s",)
    if raw_depth:
        notes += ("depth registered at import from raw/ (depth K + depth-to-color extrinsic)",)
    return Scene(ids, stamps, np.stack([poses[f] for f in ids]), [K] * len(ids), source,
                 SceneMeta(str(src.resolve()), NAME, VERSION, notes=notes))
