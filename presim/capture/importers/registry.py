"""Importer registry, format auto-detection and the one import entry point.

Every importer module has ``NAME``, ``detect(src: Path) -> bool`` and
``read(src: Path, every: int, max_frames: int | None) -> Scene`` (lazy frames, no point cloud, original
world frame). :func:`import_capture` picks the importer, fuses the point cloud and aligns the floor; a capture
without poses gets them from the ``estimate_poses`` function its caller passes.
"""

from __future__ import annotations

import importlib
from dataclasses import replace
from pathlib import Path
from types import ModuleType
from typing import Callable

import numpy as np

from presim.capture.floor import FloorConfig, align_scene_to_floor, gravity_from_cameras
from presim.capture.importers.common import override_depth_scale
from presim.capture.scene import Scene, SceneError, check_scene_geometry
from presim.capture.store import fuse_point_cloud

__all__ = ["FORMATS", "importer", "detect_format", "import_capture"]

# Detection order matters: APC shelf folders also hold frame-*.color.png, so they are tried first.
FORMATS: dict[str, str] = {
    "apc_shelf": "presim.capture.importers.apc_shelf",
    "kinfu": "presim.capture.importers.kinfu",
    "tum": "presim.capture.importers.tum",
    "colmap": "presim.capture.importers.colmap",
    "nerfstudio": "presim.capture.importers.nerfstudio",
    "bop": "presim.capture.importers.bop",
    "ycbv": "presim.capture.importers.ycbv",
}
ALIASES = {"7scenes": "kinfu", "7-scenes": "kinfu", "kinectfusion": "kinfu", "apc": "apc_shelf",
            "ycb-video": "ycbv", "ycb_video": "ycbv", "nerf": "nerfstudio", "transforms": "nerfstudio"}


def importer(fmt: str) -> ModuleType:
    """The importer module of format ``fmt`` (names in :data:`FORMATS` or a known alias)."""
    name = ALIASES.get(fmt.lower(), fmt.lower())
    if name not in FORMATS:
        raise ValueError(f"unknown capture format {fmt!r}; known formats: {', '.join(FORMATS)}")
    return importlib.import_module(FORMATS[name])


def detect_format(src: str | Path) -> str:
    """Name of the first importer that recognises ``src``; a ValueError listing formats otherwise."""
    src = Path(src)
    if not src.exists():
        raise FileNotFoundError(f"{src}: capture not found")
    for name in FORMATS:
        if importer(name).detect(src):
            return name
    if (src / "scene.json").is_file():
        raise ValueError(f"{src}: this is already a PreSim scene (scene.json); use it directly, e.g. `presim info {src}`")
    raise ValueError(
        f"{src}: no importer recognises this capture. Known formats: "
        "kinfu (frame-*.color.png + frame-*.pose.txt + camera-intrinsics.txt), "
        "apc_shelf (cam.info.txt + frame-*.depth.png), tum (rgb.txt + depth.txt + groundtruth.txt), "
        "colmap (cameras/images .txt|.bin [+ sparse/0/] + depth maps), nerfstudio (transforms.json), "
        "bop (scene_camera.json + rgb/ + depth/), ycbv (*-meta.mat + *-color.png + *-depth.png). "
        "Pass --format to force one.")


def import_capture(src: str | Path, fmt: str | None = None, every: int = 1, max_frames: int | None = None,
                   gravity: np.ndarray | None = None, align_floor: bool = True,
                   floor_config: FloorConfig = FloorConfig(), voxel_m: float = 0.01,
                   estimate_poses: Callable[[Scene], Scene] | None = None,
                   depth_scale_mm: float | None = None) -> Scene:
    """Read a capture folder into a :class:`Scene` (frames stay on disk, read lazily).

    Args:
        src: capture folder (or file, for formats that are one file).
        fmt: format name (see :data:`FORMATS`); auto-detected when None.
        every, max_frames: keep frames 0, every, 2*every, ... and at most ``max_frames`` of them.
        gravity: gravity direction (3,) in the capture's world frame when known.
        align_floor: estimate the floor and move the world to gravity -z / floor z = 0 when found.
        floor_config: floor search thresholds.
        voxel_m: voxel size of the fused point cloud.
        estimate_poses: for a capture without poses, the function that gives its frames poses (e.g.
            :func:`presim.align.sfm.estimate_poses`: pycolmap SfM, then alignment; pose estimation
            sits above ``capture``, so the caller passes it). None: such a capture is refused.
        depth_scale_mm: millimetres per step of the depth images, replacing the format's unit (needed
            for 8-bit depth images, which are refused otherwise).

    Returns:
        The scene, with its point cloud; ``scene.meta.transforms`` lists any change of world frame.

    Example:
        >>> scene = import_capture("../shared/data/apc_cardboard_bin_kinfu50")   # doctest: +SKIP
        >>> len(scene), scene.meta.source_format                                 # doctest: +SKIP
        (50, 'kinfu')
    """
    src = Path(src)
    if not src.exists():
        raise FileNotFoundError(f"{src}: capture not found")
    if fmt is None and src.is_dir() and not any(importer(n).detect(src) for n in FORMATS) \
            and (src / "capture").is_dir():
        # `presim drive --record DIR` writes its capture (kinfu layout) to DIR/capture.
        src = src / "capture"
    name = detect_format(src) if fmt is None else importer(fmt).NAME
    scene = importer(name).read(src, every=every, max_frames=max_frames)
    if depth_scale_mm is not None:
        override_depth_scale(scene.frames, depth_scale_mm, str(src))
    if scene.poses_source == "none":
        if estimate_poses is None:
            raise SceneError(f"{src}: the capture has no camera poses; `presim import SRC DST` estimates them "
                             "(pycolmap SfM), or pass estimate_poses=presim.align.sfm.estimate_poses")
        scene = estimate_poses(scene)
    check_scene_geometry(scene.T_world_cam, scene.intrinsics, scene.frame_ids, str(src))
    if gravity is not None:
        gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(gravity)) or np.linalg.norm(gravity) < 1e-9:
            raise ValueError(f"gravity must be a finite non-zero vector, got {gravity.tolist()}")
    if not align_floor:
        if gravity is not None:
            g, how = gravity / np.linalg.norm(gravity), "given"
        else:
            g, cons = gravity_from_cameras(scene.T_world_cam)
            how = f"estimated from camera up axes, consistency {cons:.2f}"
        return replace(scene, gravity_world=g, meta=replace(
            scene.meta, notes=scene.meta.notes + (f"floor alignment disabled; gravity {how}",)))
    if scene.points is None:
        scene = replace(scene, points=fuse_point_cloud(scene, voxel_m=voxel_m))
    if len(scene.points) == 0:
        raise SceneError(f"{src}: no valid depth in any frame")
    return align_scene_to_floor(scene, gravity, floor_config)
