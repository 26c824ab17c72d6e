"""The BOP dataset job: sample camera poses around targets, synthesize RGB-D, annotate, write.

One call of :func:`generate_bop` writes one BOP scene ``OUT/<split>/<scene_id:06d>/`` of
``config.frames`` images (thesis §5.3.6-5.3.7). Frame slot ``k`` (image ``im_id = k``) targets object
``objects[k % n]``; its attempt ``a`` draws everything from ``rng(seed, k, a)``: a seed view that sees
the target, a perturbed pose, the truncation/clearance checks (cheap: the target model alone), then
the synthesized RGB-D and the annotations of every object; the attempt is dropped when the target's
``visib_fract`` is below ``min_visib_fract``. A slot whose ``max_attempts`` attempts all fail is left
out (counted in the report). Every slot is a pure function of (job, k), so any worker -- a local
process or a Ray actor -- produces the same bytes.

Resumable and atomic: each frame's images are written atomically, then its record
(``.presim_work/frame_KKKKKK.json``, the frame's completion marker). A rerun of the same job skips
recorded slots. The scene's JSON files, the report and the completion marker
(``.presim_complete``) are written only when every slot is done, so a partial scene never has a
``scene_gt.json`` and is never mistaken for a finished one. A different job on the same folder is
refused unless ``overwrite``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import multiprocessing as mp
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np

from presim.capture.store import load_scene
from presim.datasets import bop_writer
from presim.datasets.annotate import AnnotateConfig, annotate_instances, render_model_depth
from presim.datasets.camera_sampling import (
    CameraSamplingConfig, check_candidate, frame_rng, output_intrinsics, perturb_pose, seed_views,
)
from presim.datasets.object_sources import PlacedObject
from presim.datasets.objects import merge_models_dir
from presim.datasets.real_split import FrameRanges, frame_positions
from presim.geometry import Intrinsics, compose, invert, transform_points
from presim.io_utils import LOCK_FILE, atomic_write_bytes, atomic_write_json, folder_lock, progress
from presim.synthesis.renderer import RenderConfig, Renderer

__all__ = ["GenConfig", "GenJob", "FrameOutput", "FrameGenerator", "GenReport", "generate_bop",
           "WORK_DIR", "COMPLETE_MARKER", "MAX_FRAMES", "report_path", "check_depth_scale"]

WORK_DIR = ".presim_work"
COMPLETE_MARKER = ".presim_complete"
MAX_FRAMES = 999_999
"""Image slots of one BOP scene: BOP names images by 6-digit ids (``rgb/000000.png``)."""
MIN_DEPTH_RANGE_M = 1.0
"""A depth PNG unit must let 16 bits reach at least this far (``--depth-scale`` >= 0.0153 mm)."""
MAX_DEPTH_SCALE_MM = 100.0
"""Coarsest depth PNG unit accepted (10 cm per step: coarser flattens every object)."""


def check_depth_scale(depth_scale_mm: float, flag: str = "--depth-scale") -> None:
    """Refuse a depth PNG unit (mm per step) whose 16 bits cannot hold :data:`MIN_DEPTH_RANGE_M`
    (every depth beyond it would be clipped to invalid, and frames dropped) or that is coarser than
    :data:`MAX_DEPTH_SCALE_MM`; the message starts with ``flag``."""
    import math

    from presim.limits import InputError

    try:
        v = float(depth_scale_mm)
    except (TypeError, ValueError):
        raise InputError(flag, f"must be a number of millimetres per depth PNG step, got {depth_scale_mm!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(flag, f"must be a positive finite number of millimetres per step, got {depth_scale_mm!r}")
    if 65535 * v / 1000.0 < MIN_DEPTH_RANGE_M:
        raise InputError(flag, f"{v:g} mm per step stores depths up to {65535 * v / 1000.0:.3g} m only; at least "
                               f"{MIN_DEPTH_RANGE_M * 1000 / 65535:.4f} is needed to reach {MIN_DEPTH_RANGE_M:g} m "
                               "(BOP uses 0.1: 0.1 mm steps up to 6.55 m, or 1.0: 1 mm up to 65.5 m)")
    if v > MAX_DEPTH_SCALE_MM:
        raise InputError(flag, f"{v:g} mm per step is coarser than {MAX_DEPTH_SCALE_MM:g} mm; objects would be flat")


@dataclass(frozen=True)
class GenConfig:
    """What to generate (defaults = thesis §5.3.6-5.3.7: 1280x720, rotation <= 30 deg, translation <= 0.2 m)."""

    frames: int = 100
    """Number of image slots (images in the scene unless a slot fails every attempt)."""
    seed: int = 0
    """Seed of every random choice; same seed + same inputs = same dataset, byte for byte."""
    width: int = 1280
    """Generated image width, pixels."""
    height: int = 720
    """Generated image height, pixels."""
    hfov_deg: float | None = None
    """Horizontal field of view; None = the scene camera's."""
    split: str = "train"
    """BOP split folder (``train``, ``test``, ``val``, ...)."""
    scene_id: int = 0
    """BOP scene id (folder ``<split>/<scene_id:06d>``)."""
    image_format: str = "png"
    """``png`` or ``jpg`` color images."""
    depth_scale: float = bop_writer.DEFAULT_DEPTH_SCALE
    """depth_mm = depth PNG value x depth_scale (0.1: 0.1 mm steps, up to 6.55 m)."""
    min_visib_fract: float = 0.1
    """A frame is dropped when the target's visible fraction is below this (thesis §5.3.6)."""
    max_attempts: int = 20
    """Attempts per frame slot before it is given up."""
    keep_filled_depth: bool = False
    """Write the renderer's hole-filled depth too (default: 0 where no view covered the pixel, so
    depth PNGs and px_count_valid agree)."""
    coco: bool = False
    """Also write ``scene_gt_coco.json`` (COCO instances of the visible masks)."""
    sampling: CameraSamplingConfig = CameraSamplingConfig()
    """Camera pose sampling around seed views."""
    annotate: AnnotateConfig = AnnotateConfig()
    """Mask / visibility / box computation."""
    source_frames: FrameRanges | None = None
    """Capture frame positions the synthesis may use as seed and source views (union of Python
    slices, ``real_split.parse_frame_range``; None = all). Keeps held-out capture frames out of a
    synthesized training set (the Table 4.5 protocol in docs/pose-networks.md)."""

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size too small: {self.width}x{self.height}")
        if self.image_format not in ("png", "jpg"):
            raise ValueError(f"image format must be png or jpg, got {self.image_format!r}")
        if not 0.0 <= self.min_visib_fract <= 1.0:
            raise ValueError(f"min_visib_fract must be in [0, 1], got {self.min_visib_fract}")
        check_depth_scale(self.depth_scale, "depth_scale")
        if self.frames > MAX_FRAMES:
            raise ValueError(f"frames: at most {MAX_FRAMES} per BOP scene (6-digit image ids), got {self.frames}")
        if self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {self.max_attempts}")


@dataclass(frozen=True)
class GenJob:
    """Everything a worker needs to make any frame (picklable; shipped to processes and Ray actors).
    The scene folder must be readable at ``scene_path`` on every worker."""

    scene_path: str
    objects: tuple[PlacedObject, ...]
    config: GenConfig
    render_config: object | None = None
    """``presim.synthesis.renderer.RenderConfig`` (None = its defaults)."""
    scene_poses: str = "auto"
    """Camera poses of the scene: ``store.load_scene(poses=...)`` ("auto": refined when present)."""

    def fingerprint(self) -> str:
        """Hash of everything that changes the output (scene, objects, config)."""
        h = hashlib.sha256()
        scene_json = Path(self.scene_path) / "scene.json"
        h.update(scene_json.read_bytes() if scene_json.is_file() else self.scene_path.encode())
        for o in self.objects:
            h.update(str(o.obj_id).encode())
            h.update(o.model.vertices_m.tobytes())
            if o.model.faces is not None:
                h.update(o.model.faces.tobytes())
            h.update(np.asarray(o.T_world_obj, dtype=np.float64).tobytes())
        h.update(json.dumps(_config_dict(self.config), sort_keys=True).encode())
        h.update(repr(self.render_config).encode())
        refined = Path(self.scene_path) / "poses_refined.json"
        if self.scene_poses != "given" and refined.is_file():  # refined poses change every image
            h.update(refined.read_bytes())
        return h.hexdigest()[:16]


def source_scene(scene_path: str | Path, scene_poses: str, source_frames: FrameRanges | None):
    """The scene restricted to the capture frames the synthesis may use (``GenConfig.source_frames``)."""
    scene = load_scene(scene_path, poses=scene_poses)
    if source_frames is None:
        return scene
    idx = frame_positions(source_frames, len(scene))
    if not idx:
        ranges = ",".join(":".join(map(str, r)) for r in source_frames)
        raise ValueError(f"--source-frames {ranges} selects no frame of the {len(scene)} in {scene_path}")
    return scene.subset(idx)


def _config_dict(c: GenConfig) -> dict:
    return asdict(c)


@dataclass
class FrameOutput:
    """What a worker returns for one slot: encoded files (relative to the scene folder) and the
    frame record (None when every attempt failed)."""

    slot: int
    files: dict[str, bytes]
    record: dict


class FrameGenerator:
    """Per-worker state: the scene, one Renderer, the models, seed views, a KD-tree of the scene.

    Build it once per process; :meth:`run` makes any slot.
    """

    def __init__(self, job: GenJob):
        from scipy.spatial import cKDTree

        self.job = job
        self.cfg = job.config
        self.scene = source_scene(job.scene_path, job.scene_poses, self.cfg.source_frames)
        self.renderer = Renderer(self.scene, job.render_config if job.render_config is not None else RenderConfig())
        self.K = output_intrinsics(self.scene.intrinsics[0], self.cfg.width, self.cfg.height, self.cfg.hfov_deg)
        self.objects = list(job.objects)
        self.models = {o.obj_id: o.model for o in self.objects}
        self.seeds = {o.obj_id: seed_views(self.scene, o.model, o.T_world_obj, self.cfg.sampling) for o in self.objects}
        pts = self.scene.points.xyz if self.scene.points is not None and len(self.scene.points) else None
        self.tree = cKDTree(pts) if pts is not None else None

    def run(self, slot: int) -> FrameOutput:
        cfg = self.cfg
        target = self.objects[slot % len(self.objects)]
        seeds = self.seeds[target.obj_id]
        rejected: dict[str, int] = {}
        c_world = transform_points(target.T_world_obj, target.model.center_m[None])[0]
        record: dict = {"im_id": int(slot), "target_obj_id": int(target.obj_id), "ok": False}
        if len(seeds) == 0:
            record.update(rejected={"no_seed_view": 1}, attempts=0)
            return FrameOutput(slot, {}, record)
        for attempt in range(cfg.max_attempts):
            rng = frame_rng(cfg.seed, slot, attempt)
            seed_idx = int(seeds[rng.integers(len(seeds))])
            T_world_cam = perturb_pose(rng, self.scene.T_world_cam[seed_idx], cfg.sampling)
            T_cam_world = invert(T_world_cam)
            r = render_model_depth(target.model, compose(T_cam_world, target.T_world_obj), self.K, cfg.annotate)
            px_all = int(np.count_nonzero(r.depth_m))
            px_in = int(np.count_nonzero(r.in_image(self.K))) if px_all else 0
            why = check_candidate(T_world_cam, px_in, px_all, c_world, target.model.radius_m, self.scene,
                                  self.tree, cfg.sampling)
            if why is not None:
                rejected[why] = rejected.get(why, 0) + 1
                continue
            rgbd = self.renderer.render(T_world_cam, self.K)
            instances = [(o.obj_id, compose(T_cam_world, o.T_world_obj)) for o in self.objects]
            anns = annotate_instances(self.models, instances, self.K, rgbd.depth_m, rgbd.valid, cfg.annotate)
            tgt = next(a for a in anns if a.obj_id == target.obj_id)
            if tgt.visib_fract < cfg.min_visib_fract:
                rejected["target_not_visible"] = rejected.get("target_not_visible", 0) + 1
                continue
            # Instances whose silhouette touches the image, in object-id order (their mask index).
            anns = [a for a in anns if a.mask.any()]
            depth = rgbd.depth_m if cfg.keep_filled_depth else np.where(rgbd.valid, rgbd.depth_m, 0.0)
            files, n_clip = bop_writer.encode_frame(slot, rgbd.color, depth.astype(np.float32), anns,
                                                    cfg.depth_scale, cfg.image_format)
            record.update(
                ok=True, attempts=attempt + 1, rejected=rejected, seed_view=int(seed_idx),
                depth_clipped_px=n_clip, hole_frac_before_fill=float(rgbd.hole_frac_before_fill),
                scene_camera=bop_writer.scene_camera_entry(self.K, T_world_cam, cfg.depth_scale),
                scene_gt=[a.gt_dict() for a in anns], scene_gt_info=[a.gt_info_dict() for a in anns],
            )
            if cfg.coco:
                record["coco_rle"] = [bop_writer.coco_rle(a.mask_visib) for a in anns]
            return FrameOutput(slot, files, record)
        record.update(attempts=cfg.max_attempts, rejected=rejected)
        return FrameOutput(slot, {}, record)


# ---- executors ----------------------------------------------------------------------------------

_WORKER: FrameGenerator | None = None


def _init_worker(job: GenJob, numba_threads: int) -> None:
    global _WORKER
    os.environ.setdefault("PRESIM_NO_PROGRESS", "1")
    import numba

    # The renderer's kernels are numba-parallel: split the cores between the processes instead of
    # letting every process start one thread per core (oversubscription halved throughput).
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS, numba_threads)))
    _WORKER = FrameGenerator(job)


def _run_slot(slot: int) -> FrameOutput:
    assert _WORKER is not None
    return _WORKER.run(slot)


def _run_serial(job: GenJob, slots: Sequence[int]) -> Iterator[FrameOutput]:
    gen = FrameGenerator(job)
    for k in slots:
        yield gen.run(k)


def _run_processes(job: GenJob, slots: Sequence[int], workers: int) -> Iterator[FrameOutput]:
    # spawn: numba/open3d/ray threads make fork unsafe; each process builds its Renderer once.
    ctx = mp.get_context("spawn")
    threads = max(1, (os.cpu_count() or 1) // workers)
    with ctx.Pool(workers, initializer=_init_worker, initargs=(job, threads)) as pool:
        yield from pool.imap_unordered(_run_slot, slots, chunksize=1)


class _RayFrameWorker:
    def __init__(self, job: GenJob):
        os.environ.setdefault("PRESIM_NO_PROGRESS", "1")
        self.gen = FrameGenerator(job)

    def run(self, slot: int) -> FrameOutput:
        return self.gen.run(slot)


def _ray_init(address: str):
    import ray

    if ray.is_initialized():
        return ray, False
    if address == "local":
        # A private local instance with node IP 127.0.0.1 and no dashboard. Ray 2.60's GCS/raylet
        # still listen on all interfaces (docs/datasets.md); process workers open no socket.
        ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
                 log_to_driver=False, configure_logging=False)
    else:
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    return ray, True


def _run_ray(job: GenJob, slots: Sequence[int], address: str, workers: int) -> Iterator[FrameOutput]:
    ray, started = _ray_init(address)
    try:
        from ray.util import ActorPool

        n = max(1, min(workers, len(slots)))
        Actor = ray.remote(num_cpus=1)(_RayFrameWorker)
        actors = [Actor.remote(job) for _ in range(n)]
        pool = ActorPool(actors)
        yield from pool.map_unordered(lambda a, k: a.run.remote(k), list(slots))
        for a in actors:
            ray.kill(a)
    finally:
        if started:
            ray.shutdown()


# ---- the job ------------------------------------------------------------------------------------

@dataclass
class GenReport:
    """Summary of a job (also written as JSON next to the dataset)."""

    out: str
    scene_dir: str
    frames_requested: int
    frames_written: int
    slots_failed: list[int] = field(default_factory=list)
    attempts: int = 0
    dropped_not_visible: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    instances: int = 0
    instances_per_object: dict[str, int] = field(default_factory=dict)
    mean_target_visib_fract: float = 0.0
    depth_clipped_px: int = 0
    finished: bool = False
    """Every slot was tried: the scene's JSON files and the completion marker are written."""
    complete: bool = False
    """Finished with every requested frame written (``frames_written == frames_requested``)."""
    fingerprint: str = ""
    seconds: float = 0.0
    frames_per_s: float = 0.0
    workers: int = 1
    backend: str = "serial"


def report_path(out: Path, split: str, scene_id: int) -> Path:
    """Report JSON next to the dataset: ``OUT/gen_bop_report_<split>_<scene_id:06d>.json``."""
    return Path(out) / f"gen_bop_report_{split}_{int(scene_id):06d}.json"


def _write_dataset_level(out: Path, K: Intrinsics, objects: Sequence[PlacedObject], depth_scale: float) -> None:
    cam = bop_writer.camera_json(K, depth_scale)
    cam_path = out / "camera.json"
    if cam_path.is_file():
        old = json.loads(cam_path.read_text())
        if old != cam:
            raise ValueError(f"{cam_path}: the dataset already has a different camera ({old}); "
                             f"write to another --out or use the same size/field of view/depth scale")
    else:
        atomic_write_json(cam_path, cam)
    merge_models_dir(out, objects)


def _store(sdir: Path, work: Path, fo: FrameOutput) -> None:
    bop_writer.write_frame_files(sdir, fo.files)
    # The record last: it marks the frame's files complete.
    atomic_write_json(work / f"frame_{fo.slot:06d}.json", fo.record, indent=None)


def generate_bop(scene_path: str | Path, out: str | Path, objects: Sequence[PlacedObject],
                 config: GenConfig = GenConfig(), workers: int = 1, ray_address: str | None = None,
                 render_config=None, overwrite: bool = False, stop_after: int | None = None,
                 show_progress: bool | None = None, scene_poses: str = "auto", wait: bool = True) -> GenReport:
    """Generate (or resume) one BOP scene. See the module docstring.

    Args:
        scene_path: saved PreSim scene folder.
        out: BOP dataset root (created).
        objects: placed object models (:func:`presim.datasets.object_sources.resolve_objects`).
        config: what to generate.
        workers: local worker processes (1 = in this process); with ``ray_address``, Ray actors.
        ray_address: ``"local"`` (a private Ray instance, node IP 127.0.0.1) or a cluster address.
        render_config: ``RenderConfig`` of the view synthesis (None = defaults).
        overwrite: replace a scene folder made by a different job.
        stop_after: make at most this many new frames, then return without finishing (time-sliced
            jobs; rerun to continue). The report then has ``finished = complete = False``.
        wait: when another process is generating into the same scene folder, wait for it (a
            message on stderr) instead of raising :class:`~presim.io_utils.FolderBusyError`.
        show_progress: progress bar (None = unless PRESIM_NO_PROGRESS=1).
        scene_poses: the scene's camera poses (``store.load_scene(poses=...)``: "auto" = refined by
            ``presim align`` when present, "given", "refined").

    Returns:
        The :class:`GenReport` (also written to :func:`report_path` when the scene is complete).
    """
    t0 = time.perf_counter()
    scene_path = Path(scene_path).resolve()
    out = Path(out)
    if not objects:
        raise ValueError("no objects to annotate")
    job = GenJob(str(scene_path), tuple(objects), config, render_config, scene_poses)
    fp = job.fingerprint()
    sdir = bop_writer.scene_dir(out, config.split, config.scene_id)
    sdir.mkdir(parents=True, exist_ok=True)
    # One job per scene folder at a time: a second run waits, then finds the scene finished (or
    # resumes it) instead of writing frame records into a work folder the first one removed.
    with folder_lock(sdir, f"presim gen-bop (scene {config.split}/{config.scene_id:06d})", wait=wait):
        return _generate_locked(job, fp, scene_path, out, sdir, objects, config, workers, ray_address,
                                overwrite, stop_after, show_progress, scene_poses, t0)


def _clear_dir(d: Path) -> None:
    """Remove everything in ``d`` but its lock file."""
    for p in d.iterdir():
        if p.name == LOCK_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def _generate_locked(job: GenJob, fp: str, scene_path: Path, out: Path, sdir: Path, objects, config: GenConfig,
                     workers: int, ray_address: str | None, overwrite: bool, stop_after: int | None,
                     show_progress: bool | None, scene_poses: str, t0: float) -> GenReport:
    work = sdir / WORK_DIR
    marker = sdir / COMPLETE_MARKER
    rpath = report_path(out, config.split, config.scene_id)

    if marker.is_file():
        if marker.read_text().strip() == fp and not overwrite:
            if rpath.is_file():
                rep = GenReport(**json.loads(rpath.read_text()))
            else:
                rep = GenReport(str(out), str(sdir), config.frames, 0, fingerprint=fp)
            rep.finished = True
            rep.complete = rep.frames_written == rep.frames_requested
            return rep
        if not overwrite:
            raise FileExistsError(f"{sdir}: holds a finished scene of a different job (fingerprint "
                                  f"{marker.read_text().strip()} != {fp}); pass overwrite / --overwrite")
    job_file = work / "job.json"
    if job_file.is_file() and json.loads(job_file.read_text()).get("fingerprint") != fp and not overwrite:
        raise FileExistsError(f"{sdir}: an unfinished run of a different job is there; pass overwrite / "
                              f"--overwrite to discard it")
    if overwrite and (marker.is_file() or job_file.is_file()):
        _clear_dir(sdir)
    elif not job_file.is_file() and any(p.name != LOCK_FILE for p in sdir.iterdir()):
        raise FileExistsError(f"{sdir}: not empty and not made by gen-bop; choose another --out")
    work.mkdir(parents=True, exist_ok=True)
    atomic_write_json(job_file, {"fingerprint": fp, "scene": str(scene_path), "config": _config_dict(config)})

    # Dataset-level files are deterministic: (re)writing them on resume changes nothing.
    scene = source_scene(scene_path, scene_poses, config.source_frames)
    K = output_intrinsics(scene.intrinsics[0], config.width, config.height, config.hfov_deg)
    _write_dataset_level(out, K, objects, config.depth_scale)
    del scene

    # The slots still to make, as a lazy iterator (never a list of `frames` entries).
    done = _recorded_slots(work, config.frames)
    n_todo = config.frames - len(done)
    if stop_after is not None:
        n_todo = min(n_todo, max(0, int(stop_after)))
    todo = itertools.islice((k for k in range(config.frames) if k not in done), n_todo)
    backend = "ray" if ray_address else ("processes" if workers > 1 else "serial")
    if n_todo:
        if ray_address:
            it: Iterable[FrameOutput] = _run_ray(job, list(todo), ray_address, max(1, workers))
        elif workers > 1:
            it = _run_processes(job, todo, min(workers, n_todo))
        else:
            it = _run_serial(job, todo)
        bar = progress(total=n_todo, desc=f"gen-bop {sdir.name}", unit="frame",
                       disable=None if show_progress is None else not show_progress)
        try:
            for fo in it:
                _store(sdir, work, fo)
                bar.update(1)
        finally:
            bar.close()
    t_gen = time.perf_counter() - t0

    records = []
    for k in range(config.frames):
        p = work / f"frame_{k:06d}.json"
        if p.is_file():
            records.append(json.loads(p.read_text()))
    rep = _report(out, sdir, config, records, fp, backend, max(1, workers))
    rep.seconds = round(t_gen, 3)
    rep.frames_per_s = round(n_todo / t_gen, 4) if t_gen > 0 and n_todo else 0.0
    if len(records) < config.frames:
        return rep  # stopped early: no scene JSON, no marker

    ok = [r for r in records if r.get("ok")]
    coco = None
    if config.coco:
        rles = {(r["im_id"], k): rle for r in ok for k, rle in enumerate(r.get("coco_rle", []))}
        coco = bop_writer.coco_scene(ok, rles, [o.model for o in objects], K.width, K.height,
                                     f".{config.image_format}", config.min_visib_fract)
    bop_writer.write_scene_json(sdir, ok, coco)
    rep.finished = True
    rep.complete = rep.frames_written == rep.frames_requested
    atomic_write_json(rpath, asdict(rep))
    atomic_write_bytes(marker, (fp + "\n").encode())
    shutil.rmtree(work, ignore_errors=True)
    return rep


def _recorded_slots(work: Path, frames: int) -> set[int]:
    """Slots below ``frames`` whose frame record is in the work folder."""
    done: set[int] = set()
    if work.is_dir():
        for e in os.scandir(work):
            name = e.name
            if name.startswith("frame_") and name.endswith(".json") and name[6:-5].isdigit():
                k = int(name[6:-5])
                if k < frames:
                    done.add(k)
    return done


def _report(out: Path, sdir: Path, config: GenConfig, records: list[dict], fp: str, backend: str,
            workers: int) -> GenReport:
    rep = GenReport(out=str(out), scene_dir=str(sdir), frames_requested=config.frames, frames_written=0,
                    fingerprint=fp, backend=backend, workers=workers)
    vis = []
    for r in records:
        rep.attempts += int(r.get("attempts", 0))
        for k, v in r.get("rejected", {}).items():
            rep.rejected[k] = rep.rejected.get(k, 0) + int(v)
        if not r.get("ok"):
            rep.slots_failed.append(int(r["im_id"]))
            continue
        rep.frames_written += 1
        rep.depth_clipped_px += int(r.get("depth_clipped_px", 0))
        for gt, info in zip(r["scene_gt"], r["scene_gt_info"]):
            rep.instances += 1
            key = str(gt["obj_id"])
            rep.instances_per_object[key] = rep.instances_per_object.get(key, 0) + 1
            if gt["obj_id"] == r["target_obj_id"]:
                vis.append(info["visib_fract"])
    rep.dropped_not_visible = rep.rejected.get("target_not_visible", 0)
    rep.mean_target_visib_fract = round(float(np.mean(vis)), 4) if vis else 0.0
    rep.instances_per_object = dict(sorted(rep.instances_per_object.items(), key=lambda kv: int(kv[0])))
    return rep
