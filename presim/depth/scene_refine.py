"""Refine the depth of many frames of a scene into one ``.npy`` file, in parallel and resumably.

``presim refine SCENE`` writes ``SCENE/depth_refined.npy`` (float32 (N, H, W), metres, 0 = unknown);
the raw ``depth.npy`` is never touched. While running, rows go into ``<out>.partial`` (a memory-mapped
``.npy``) and each finished frame leaves a marker in ``<out>.done/``; an interrupted run resumes from
the markers (if the configuration is unchanged), and the file is renamed into place only when every
frame is done. Workers are separate processes (one numba thread each) that load the scene themselves
(memory-mapped), so frames never travel between processes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np

from presim.capture.scene import Scene
from presim.capture.store import load_scene, set_has_refined_depth
from presim.depth.refine import RefineConfig, RefView, refine_depth, reference_weights, select_reference_views
from presim.io_utils import atomic_write_json, open_npy_for_writing, progress

__all__ = ["refine_frames_to_file", "refine_scene", "refine_one_frame", "config_key"]


def config_key(config: RefineConfig) -> dict:
    """The fields of ``config`` that change the result (for fingerprints and cache keys): without
    ``backend``, and without the sharpness-reference fields while ``sharp_refs`` is off (so results
    computed before those fields existed keep their keys)."""
    d = dataclasses.asdict(config)
    d.pop("backend", None)
    if not d.get("sharp_refs"):
        d.pop("sharp_refs", None)
        d.pop("sharp_refs_gamma", None)
    return d


def refine_one_frame(scene: Scene, idx: int, ref_pool: Sequence[int], config: RefineConfig) -> np.ndarray:
    """Refined depth (float32 (H, W)) of frame ``idx`` with references chosen from ``ref_pool``."""
    refs = select_reference_views(scene.T_world_cam, idx, ref_pool, config.num_refs, config.max_ref_angle_deg)
    f = scene.frame(idx)
    loaded = [scene.frames.load(j) for j in refs]
    weights = (reference_weights([c for c, _ in loaded], config.sharp_refs_gamma) if config.sharp_refs
               else [1.0] * len(refs))
    views = [RefView(c, d, scene.intrinsics[j], scene.T_world_cam[j], w)
             for j, (c, d), w in zip(refs, loaded, weights)]
    return refine_depth(f.color, f.depth_m, f.K, f.T_world_cam, views, config).depth_m


# ---- worker process state ------------------------------------------------------------------------
_W: dict = {}


def _init_worker(scene_path: str, partial: str, done_dir: str, config: RefineConfig, poses: str = "auto") -> None:
    import numba

    numba.set_num_threads(1)  # parallelism comes from the processes
    _W.update(scene=load_scene(scene_path, poses=poses), partial=partial, done=Path(done_dir), config=config)


def _work(task: tuple[int, int, list[int]]) -> int:
    row, idx, pool = task
    depth = refine_one_frame(_W["scene"], idx, pool, _W["config"])
    _write_row(Path(_W["partial"]), _W["done"], row, depth)
    return row


def _write_row(partial: Path, done: Path, row: int, depth: np.ndarray) -> None:
    arr = np.load(partial, mmap_mode="r+")
    arr[row] = depth
    arr.flush()
    del arr
    # The marker is written after the row is flushed: a marker always means a complete row.
    (done / f"{row:06d}").write_text("ok\n")


def _fingerprint(scene: Scene, indices: list[int], ref_pool: list[int], config: RefineConfig) -> str:
    d = {"config": dataclasses.asdict(config), "indices": indices, "ref_pool": ref_pool,
         "frames": list(scene.frame_ids), "shape": [len(indices), scene.height, scene.width]}
    d["config"] = config_key(config)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def refine_frames_to_file(scene: Scene, out_path: str | Path, indices: Sequence[int] | None = None,
                          ref_pool: Sequence[int] | None = None, config: RefineConfig = RefineConfig(),
                          workers: int = 1, overwrite: bool = False, max_frames: int | None = None,
                          desc: str = "refine") -> Path | None:
    """Refine frames ``indices`` (default: all) of ``scene`` with references from ``ref_pool``
    (default: ``indices``) into ``out_path`` (float32 (len(indices), H, W) ``.npy``).

    Resumable: rows already marked done in ``<out>.done/`` are kept when the configuration is the
    same. ``max_frames`` stops after that many newly refined frames (time-sliced runs; tests use it to
    simulate an interruption) and returns None while rows remain; otherwise returns ``out_path``
    once the file is complete. ``workers > 1`` needs a saved scene (``scene.path``).
    """
    out = Path(out_path)
    idx = list(range(len(scene))) if indices is None else [int(i) for i in indices]
    pool = list(idx) if ref_pool is None else [int(i) for i in ref_pool]
    if any(i < 0 or i >= len(scene) for i in idx + pool):
        raise ValueError(f"frame positions must be in [0, {len(scene)})")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to recompute)")
    partial = out.with_name(out.name + ".partial")
    done = out.with_name(out.name + ".done")
    fp = _fingerprint(scene, idx, pool, config)
    shape = (len(idx), scene.height, scene.width)
    fresh = True
    if partial.exists() and (done / "fingerprint.json").is_file():
        try:
            old = json.loads((done / "fingerprint.json").read_text())
            arr = np.load(partial, mmap_mode="r")
            fresh = old.get("fingerprint") != fp or arr.shape != shape or arr.dtype != np.float32
            del arr
        except (ValueError, OSError, json.JSONDecodeError):
            fresh = True
    if fresh:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(done, ignore_errors=True)
        if partial.exists():
            partial.unlink()
        # Every byte reserved before the first row is written: a full disk is an error here, not
        # a SIGBUS in the middle of the run.
        arr = open_npy_for_writing(partial, np.float32, shape)
        del arr
        done.mkdir(parents=True)
        atomic_write_json(done / "fingerprint.json", {"fingerprint": fp})
    todo = [r for r in range(len(idx)) if not (done / f"{r:06d}").is_file()]
    limit = len(todo) if max_frames is None else min(len(todo), max(0, int(max_frames)))
    tasks = [(r, idx[r], pool) for r in todo[:limit]]
    bar = progress(total=len(idx), desc=desc, unit="frame")
    bar.update(len(idx) - len(todo))
    try:
        if workers > 1 and len(tasks) > 1:
            if scene.path is None:
                raise ValueError("parallel refinement needs a saved scene (scene.path is None)")
            ctx = mp.get_context("spawn")
            with ctx.Pool(min(workers, len(tasks)), initializer=_init_worker,
                          initargs=(str(scene.path), str(partial), str(done), config,
                                    getattr(scene, "poses_source", "auto"))) as p:
                for _ in p.imap_unordered(_work, tasks):
                    bar.update(1)
        else:
            for r, i, pl in tasks:
                _write_row(partial, done, r, refine_one_frame(scene, i, pl, config))
                bar.update(1)
    finally:
        bar.close()
    if limit < len(todo):
        return None
    os.replace(partial, out)
    shutil.rmtree(done, ignore_errors=True)
    return out


def refine_scene(scene: Scene, workers: int = 1, overwrite: bool = False,
                 config: RefineConfig = RefineConfig(), max_frames: int | None = None) -> Path | None:
    """``presim refine``: refine every frame of a saved scene into ``SCENE/depth_refined.npy``
    (references from all frames). Returns the path when complete, None if stopped by ``max_frames``."""
    if scene.path is None:
        raise ValueError("refine_scene needs a saved scene (load it with presim.capture.store.load_scene)")
    out = refine_frames_to_file(scene, Path(scene.path) / "depth_refined.npy", config=config,
                                workers=workers, overwrite=overwrite, max_frames=max_frames)
    if out is not None:
        set_has_refined_depth(scene.path)
    return out
