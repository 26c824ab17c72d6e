"""The capture's own frames as a BOP split, annotated from the camera poses and the scene's objects.

Thesis §5.3.3-5.3.5 (RobotP): the objects stand still, the camera poses are known, so each object's
pose in a frame is ``T_cam_obj = T_world_cam^-1 T_world_obj`` and its masks come from rendering its
model (reconstructed by ``presim objects`` or given) and comparing with the frame's depth, exactly as
the synthesized split (``presim gen-bop``) is annotated (:func:`presim.datasets.annotate.annotate_instances`).
The two splits share ``models/`` and object ids (both take the scene's objects).

Written per frame: ``rgb/`` (the captured colour), ``depth/`` (the captured raw depth), ``mask/``,
``mask_visib/``, and ``scene_camera.json`` (the frame's K and world pose), ``scene_gt.json``,
``scene_gt_info.json``. The scene folder is built in ``<scene>.partial`` and renamed when complete.

Example:
    >>> rep = write_real_split("out/sample", "out/bop", RealSplitConfig(split="real"))   # doctest: +SKIP
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from presim.capture.store import load_scene
from presim.datasets import bop_writer
from presim.datasets.annotate import AnnotateConfig, annotate_instances
from presim.datasets.object_sources import PlacedObject, resolve_objects
from presim.datasets.objects import merge_models_dir
from presim.geometry import compose, invert
from presim.io_utils import atomic_dir, atomic_write_json, progress

__all__ = ["RealSplitConfig", "RealSplitReport", "write_real_split", "parse_frame_range",
           "frame_positions", "FrameRanges"]


@dataclass(frozen=True)
class RealSplitConfig:
    """What :func:`write_real_split` writes."""

    split: str = "real"
    """BOP split folder."""
    scene_id: int = 0
    """BOP scene id."""
    frames: FrameRanges | None = None
    """``((start, stop, step), ...)``: the scene's frame positions (union of Python slices,
    :func:`parse_frame_range`); None = all frames."""
    depth_scale: float = bop_writer.DEFAULT_DEPTH_SCALE
    """Depth PNG unit in mm."""
    image_format: str = "png"
    refined_visibility: bool = True
    """Test visibility against the refined depth when the scene has it (the written depth PNGs are
    always the captured raw depth)."""
    annotate: AnnotateConfig = field(default_factory=AnnotateConfig)


@dataclass
class RealSplitReport:
    scene_dir: str
    frames_written: int
    instances: int
    instances_visible: int
    mean_visib_fract: float
    seconds: float


FrameRanges = tuple[tuple[int, int, int], ...]
"""Frame positions as ``((start, stop, step), ...)``: the union of Python slices."""


def parse_frame_range(text: str, flag: str = "--frames") -> FrameRanges:
    """``"A:B"``, ``"A:B:S"`` or several joined by commas (``"0:160,180:200"``): Python slices of frame
    positions (empty = open end), in the order given."""
    out = []
    for part_text in text.split(","):
        parts = part_text.split(":")
        if len(parts) not in (2, 3):
            raise ValueError(f"{flag} {text!r}: expected START:STOP[:STEP][,START:STOP...], e.g. 0:40, 40::2 "
                             f"or 0:160,180:200")
        try:
            vals = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            raise ValueError(f"{flag} {text!r}: START, STOP and STEP must be integers") from None
        start = vals[0] or 0
        stop = vals[1] if vals[1] is not None else 1 << 30
        step = vals[2] if len(vals) == 3 and vals[2] is not None else 1
        if step < 1:
            raise ValueError(f"{flag} {text!r}: STEP must be >= 1")
        if start < 0 or stop < 0:
            raise ValueError(f"{flag} {text!r}: START and STOP must be >= 0")
        out.append((start, stop, step))
    return tuple(out)


def frame_positions(frames: FrameRanges | None, n: int) -> list[int]:
    """The positions ``range(n)[start:stop:step]`` of every slice of a :func:`parse_frame_range`
    result, without repeats, in order of first appearance (None = all ``n``)."""
    if frames is None:
        return list(range(n))
    seen: dict[int, None] = {}
    for start, stop, step in frames:
        for i in range(n)[slice(start, stop, step)]:
            seen.setdefault(i, None)
    return list(seen)


def write_real_split(scene_path: str | Path, out: str | Path, config: RealSplitConfig = RealSplitConfig(),
                     objects_spec: str | None = None, overwrite: bool = False) -> RealSplitReport:
    """Write the captured frames of a scene as one BOP scene (see the module docstring).

    Args:
        scene_path: saved scene with objects (``presim objects``) or ``objects_spec``.
        out: BOP dataset root (``models/`` and ``camera.json`` shared with ``gen-bop``).
        config: see :class:`RealSplitConfig`.
        objects_spec: as ``gen-bop --objects`` (None = the scene's own objects).
        overwrite: replace an existing scene folder.
    """
    t0 = time.perf_counter()
    scene = load_scene(scene_path)
    objects = resolve_objects(scene, objects_spec)
    n = len(scene)
    idx = frame_positions(config.frames, n)
    if not idx:
        raise ValueError(f"--frames selects no frame of the {n} in {scene_path}")
    out = Path(out)
    sdir = bop_writer.scene_dir(out, config.split, config.scene_id)
    if sdir.exists() and not overwrite:
        raise FileExistsError(f"{sdir}: already exists (pass --overwrite to replace it)")
    models = {o.obj_id: o.model for o in objects}
    records = []
    n_inst = n_vis = 0
    fracs = []
    with atomic_dir(sdir, overwrite=overwrite) as tmp:
        for im_id, i in enumerate(progress(idx, desc="real split", unit="frame")):
            f = scene.frame(i)
            K = f.K
            T_cam_world = invert(f.T_world_cam)
            vis_depth = scene.depth(i, refined=config.refined_visibility)
            insts = [(o.obj_id, compose(T_cam_world, o.T_world_obj)) for o in objects]
            anns = [a for a in annotate_instances(models, insts, K, vis_depth, None, config.annotate) if a.mask.any()]
            files, _ = bop_writer.encode_frame(im_id, f.color, np.asarray(f.depth_m), anns, config.depth_scale,
                                               config.image_format)
            bop_writer.write_frame_files(tmp, files)
            n_inst += len(anns)
            n_vis += sum(a.info.px_count_visib > 0 for a in anns)
            fracs += [a.visib_fract for a in anns]
            records.append({
                "im_id": im_id,
                "scene_camera": {**bop_writer.scene_camera_entry(K, f.T_world_cam, config.depth_scale),
                                 "frame_id": scene.frame_ids[i]},
                "scene_gt": [a.gt_dict() for a in anns],
                "scene_gt_info": [a.gt_info_dict() for a in anns],
            })
        bop_writer.write_scene_json(tmp, records)
        merge_models_dir(out, objects, hint=" (the dataset was made from other objects; rerun gen-bop after `presim objects`, or write to another --out)")
        cam_path = out / "camera.json"
        if not cam_path.is_file():  # per-image cam_K in scene_camera.json is what readers use
            atomic_write_json(cam_path, bop_writer.camera_json(scene.intrinsics[0], config.depth_scale))
    return RealSplitReport(str(sdir), len(idx), n_inst, n_vis, float(np.mean(fracs)) if fracs else 0.0,
                           round(time.perf_counter() - t0, 2))
