"""Align and fuse the depth of every frame of a scene (thesis §5.3.4): ``presim fuse SCENE``.

Per frame: the sensor depth is aligned to the frame's refined depth (:func:`presim.depth.align.align_depth`)
and fused with it (:func:`presim.depth.fuse.fuse_depth`). The result goes to ``SCENE/depth_fused.npy``
(float32 (N, H, W), metres, 0 = unknown): rows are written into ``depth_fused.npy.partial`` and the
file is renamed into place only when every frame is done, so an interrupted run leaves nothing that
looks complete (a new run starts over: the whole scene takes seconds to a minute). ``depth.npy`` and
``depth_refined.npy`` are never touched.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from presim.capture.scene import Scene
from presim.capture.store import set_has_fused_depth
from presim.depth.align import AlignConfig, AlignedDepth, align_depth
from presim.depth.fuse import FuseConfig, FusedDepth, fuse_depth
from presim.geometry import Intrinsics
from presim.io_utils import progress, write_npy_atomic

__all__ = ["FUSED_FILE", "fuse_one_frame", "fuse_frames", "fuse_scene"]

FUSED_FILE = "depth_fused.npy"


def fuse_one_frame(captured_m: np.ndarray, estimated_m: np.ndarray, K: Intrinsics,
                   align: AlignConfig = AlignConfig(), fuse: FuseConfig = FuseConfig()) -> tuple[AlignedDepth, FusedDepth]:
    """Alignment (Alg. 2) then fusion (eq. 5.6-5.7) of one frame; returns both results."""
    al = align_depth(captured_m, estimated_m, K, align)
    return al, fuse_depth(al.depth_m, estimated_m, fuse, scale=al.scale)


def fuse_frames(scene: Scene, estimated: Sequence[np.ndarray] | np.ndarray, indices: Sequence[int] | None = None,
                align: AlignConfig = AlignConfig(), fuse: FuseConfig = FuseConfig(),
                out: np.ndarray | None = None, desc: str = "fuse depth") -> np.ndarray:
    """Fused depth of frames ``indices`` (default all) of ``scene``; ``estimated[k]`` is the estimate of
    ``indices[k]``. Rows go into ``out`` when given (e.g. a memory map), else a new array."""
    idx = list(range(len(scene))) if indices is None else [int(i) for i in indices]
    if len(estimated) != len(idx):
        raise ValueError(f"fuse_frames: {len(estimated)} estimated depth maps for {len(idx)} frames")
    if out is None:
        out = np.zeros((len(idx), scene.height, scene.width), np.float32)
    for k, i in enumerate(progress(idx, desc=desc, unit="frame")):
        _, fu = fuse_one_frame(scene.frames.load(i)[1], np.asarray(estimated[k]), scene.intrinsics[i], align, fuse)
        out[k] = fu.depth_m
    return out


def fuse_scene(scene: Scene, overwrite: bool = False, align: AlignConfig = AlignConfig(),
               fuse: FuseConfig = FuseConfig()) -> Path:
    """``presim fuse``: align and fuse every frame of a saved scene that has refined depth into
    ``SCENE/depth_fused.npy`` (atomic: ``.partial`` then rename). Returns the file."""
    if scene.path is None:
        raise ValueError("fuse_scene needs a saved scene (load it with presim.capture.store.load_scene)")
    if scene.depth_refined is None:
        raise ValueError(f"{scene.path}: no depth_refined.npy; run `presim refine {scene.path}` first "
                         "(the refined depth is the estimate the sensor depth is aligned to)")
    dst = Path(scene.path) / FUSED_FILE
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: already exists (pass --overwrite to recompute)")
    write_npy_atomic(dst, np.float32, (len(scene), scene.height, scene.width),
                     lambda arr: fuse_frames(scene, scene.depth_refined, align=align, fuse=fuse, out=arr))
    set_has_fused_depth(scene.path)
    return dst
