"""The sim2real depth experiment (thesis §4.5, Table 4.3) as one pure-ish entry function:

    run_depth_experiment(scene, recipe_config("default", capture_every=9), out_dir)

1. Split (:func:`split.split_capture`): capture = every N-th frame, test = all others, binned by pose
   distance to the nearest capture frame.
2. Capture sub-scene (:func:`capture_subscene`): the capture frames only, without the scene's
   refined depth, fused point cloud, floor and objects (all of those were computed from every frame).
   It is the renderer's scene and the only source of training pixels and poses.
3. Training set (:func:`build_training_set`): capture images + sensor depth at the model size, and M
   views rendered by ``Renderer.render_batch`` at :func:`split.synth_poses` (from capture poses only),
   labelled with the rendered depth where it was synthesized (``RGBD.valid``), 0 (no label) where it
   was filled. Both label sets come from the same data: the capture's sensor depth, which is also
   what the renderer warps (no refinement: it is the slowest step on 2 cores; see docs/sim2real.md).
4. Three arms, same model, same seed-initialised weights, same number of optimiser steps; every step
   draws one real batch and one synthesized batch from seeded streams shared by all arms:
   ``capture`` trains on the real batch, ``capture+synth`` on both (the same real samples per step
   plus the synthesized ones), ``synth`` on the synthesized batch only.
5. Metrics on the real test frames (sensor depth, valid pixels), per bin and overall, then mean ±
   std over seeds into ``summary.json``, ``report.md``, ``learning_curves.png``, ``examples.png``.

Resume: each (arm, seed) writes ``runs/<arm>-seed<s>.json`` (+ ``.npz`` of example predictions)
atomically when it finishes; the rendered views are cached in ``synth.npz``. A rerun with the same
configuration skips what is done; a different configuration recomputes.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from presim.capture.scene import Scene, release_frames
from presim.depth.scene_refine import refine_frames_to_file
from presim.evaluation.sim2real.metrics import DepthErrorSums
from presim.evaluation.sim2real.report import distance_curve, far_gap, report_markdown, write_figures
from presim.evaluation.sim2real.split import BINS, CaptureSplit, SynthPoseConfig, split_capture, synth_poses
from presim.io_utils import atomic_write_bytes, atomic_write_json, atomic_write_text, progress
from presim.synthesis.renderer import RenderConfig, Renderer

__all__ = ["ARMS", "RECIPES", "DepthExperimentConfig", "recipe_config", "recipe_name", "ExperimentMismatch", "code_version", "lr_factor", "TestSet", "TrainingSet", "build_training_set", "capture_subscene",
           "far_gap", "load_test_set", "refine_capture", "run_depth_experiment", "train_arm"]

ARMS = ("capture", "capture+synth", "synth")
SCHEDULES = ("cosine", "constant")
REAL_LABELS = ("rendered", "sensor")
EXPERIMENT_VERSION = 3
"""Bumped when the protocol changes (2: cosine schedule, rendered capture labels, pre-built batches;
3: per-test-frame errors in the run files)."""
_ARM_FILE = {"capture": "capture", "capture+synth": "capture_synth", "synth": "synth"}


@dataclass(frozen=True)
class DepthExperimentConfig:
    """Everything that decides the numbers of one experiment (field defaults = the ``default``
    recipe of :data:`RECIPES`; ``recipe_config("quick", ...)`` gives the small one)."""

    capture_every: int
    """Capture = scene frames 0, N, 2N, ...; all others are real test frames."""
    synth: int
    """M: number of synthesized training views."""
    steps: int = 1200
    """Optimiser steps per arm and seed (docs/sim2real.md: why 1200)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Training seeds (weights init, batch order, flips); the synthesized poses use ``pose_seed``."""
    size_wh: tuple[int, int] = (160, 120)
    """Model input/output size (images are resized; intrinsics scaled). At 64x48 the network is too
    coarse to use new viewpoints (docs/sim2real.md)."""
    batch_real: int = 8
    """Real capture frames per step (arms capture and capture+synth)."""
    batch_synth: int = 8
    """Synthesized views per step (arms capture+synth and synth)."""
    width: int = 16
    """Encoder channel width (64 = ResNet-18's channels; see model.py)."""
    lr: float = 1e-3
    """Adam peak learning rate."""
    schedule: str = "cosine"
    """Learning-rate schedule: ``cosine`` (linear warm-up over ``warmup_frac`` of the steps, then cosine
    decay to ``min_lr_frac * lr`` at the last step) or ``constant``."""
    warmup_frac: float = 0.05
    """Fraction of the steps spent warming the learning rate up linearly from ~0 (cosine schedule)."""
    min_lr_frac: float = 0.01
    """Final learning rate as a fraction of ``lr`` (cosine schedule)."""
    real_labels: str = "rendered"
    """Labels of the capture frames: ``rendered`` = the renderer's depth at the capture frame's own pose
    where it is synthesized (the same warp, splat and crack filter as the synthesized views' labels,
    so real and synthesized labels have the same density and style); ``sensor`` = the capture's
    sensor depth resized nearest-neighbour (sparser than the rendered labels at the model size).
    Test labels are always the sensor depth."""
    device: str = "cpu"
    """Torch device: ``cpu`` or ``cuda``."""
    threads: int = 1
    """Torch CPU threads (1 was fastest on the shared 2-core machine)."""
    eval_points: int = 8
    """Test metrics are also measured at this many evenly spaced steps, for the learning curves only
    (the reported model is always the one after the last step: no early stopping)."""
    max_depth_m: float = 10.0
    """Upper end of the output range and of valid ground truth."""
    pose_seed: int = 0
    """Seed of the synthesized poses (one set of views shared by all arms and training seeds)."""
    poses: SynthPoseConfig = field(default_factory=SynthPoseConfig)
    """How the synthesized poses are drawn around and between the capture poses."""
    refine: bool = False
    """Refine the capture frames' depth (thesis §3.4.1) with capture frames only as references, and
    use it for the renderer and the capture labels (test labels stay sensor depth). Slow on CPU."""

    def __post_init__(self) -> None:
        if self.synth < 1:
            raise ValueError(f"--synth must be >= 1 (M = 0 leaves the capture+synth and synth arms "
                             f"without data), got {self.synth}")
        if self.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {self.steps}")
        if not self.seeds:
            raise ValueError("--seeds needs at least one seed")
        w, h = self.size_wh
        if w < 32 or h < 32:
            raise ValueError(f"--size must be at least 32x32 (the encoder downsamples 32x), got {w}x{h}")
        if self.batch_real < 1 or self.batch_synth < 1:
            raise ValueError("batch sizes must be >= 1")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"--device must be cpu or cuda, got {self.device}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"--schedule must be one of {', '.join(SCHEDULES)}, got {self.schedule!r}")
        if self.real_labels not in REAL_LABELS:
            raise ValueError(f"--real-labels must be one of {', '.join(REAL_LABELS)}, got {self.real_labels!r}")
        if not 0.0 <= self.warmup_frac < 1.0 or not 0.0 <= self.min_lr_frac <= 1.0:
            raise ValueError("warmup_frac must be in [0, 1) and min_lr_frac in [0, 1]")

    def fingerprint(self, scene: Scene) -> str:
        """Hash of every setting that decides the numbers (not the seed list or threads), the scene
        (frames, size, the poses in use) and the experiment code (:func:`code_version`)."""
        d = asdict(self)
        d.pop("seeds")
        d.pop("threads")
        T = np.ascontiguousarray(np.asarray(scene.T_world_cam, np.float64).round(9))
        d["scene"] = [len(scene), scene.frame_ids[0], scene.frame_ids[-1], scene.width, scene.height,
                      hashlib.sha1(T.tobytes()).hexdigest()[:16]]
        d["code"] = code_version()
        return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


RECIPES: dict[str, dict] = {
    "default": dict(synth=1000, steps=1200, size_wh=(160, 120), width=16, batch_real=8, batch_synth=8),
    "quick": dict(synth=400, steps=1000, size_wh=(64, 48), width=16, batch_real=8, batch_synth=8),
}
"""Named recipes (docs/sim2real.md, "Measured"): ``default`` shows the effect of synthesized views
on sparse captures; ``quick`` (``--quick``) is the small recipe for tests and demos (about a quarter
of the CPU time per step; its gain is smaller)."""


def recipe_config(name: str, capture_every: int, **overrides) -> DepthExperimentConfig:
    """The :class:`DepthExperimentConfig` of recipe ``name`` with ``overrides`` (None values ignored)."""
    if name not in RECIPES:
        raise ValueError(f"recipe must be one of {', '.join(RECIPES)}, got {name!r}")
    kw = dict(RECIPES[name])
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return DepthExperimentConfig(capture_every=capture_every, **kw)


def recipe_name(cfg: DepthExperimentConfig) -> str:
    """The name of the recipe whose settings ``cfg`` has (any ``capture_every``), else ``custom``."""
    d = asdict(cfg)
    for name, kw in RECIPES.items():
        ref = asdict(DepthExperimentConfig(capture_every=cfg.capture_every, seeds=cfg.seeds, threads=cfg.threads,
                                           device=cfg.device, **kw))
        if ref == d:
            return name
    return "custom"


def code_version() -> str:
    """``EXPERIMENT_VERSION`` plus a hash of the sources that decide the numbers (this module, the
    model and loss, the split and poses, the metrics): a changed model or loss never resumes into
    old results."""
    here = Path(__file__).parent
    h = hashlib.sha1()
    for name in ("experiment.py", "model.py", "split.py", "metrics.py"):
        h.update((here / name).read_bytes())
    return f"v{EXPERIMENT_VERSION}-{h.hexdigest()[:12]}"


def lr_factor(step: int, cfg: DepthExperimentConfig) -> float:
    """Learning-rate multiplier for optimiser step ``step`` (0-based) of ``cfg.steps``."""
    if cfg.schedule == "constant":
        return 1.0
    warm = int(round(cfg.warmup_frac * cfg.steps))
    if step < warm:
        return (step + 1) / warm
    span = max(1, cfg.steps - 1 - warm)
    t = min(1.0, (step - warm) / span)
    return cfg.min_lr_frac + (1.0 - cfg.min_lr_frac) * 0.5 * (1.0 + math.cos(math.pi * t))


def capture_subscene(scene: Scene, split: CaptureSplit) -> Scene:
    """The scene of the capture frames only: the renderer's scene and the only training source.

    Drops what the full scene derived from all frames (test frames included): refined depth
    (references from every frame), the fused point cloud, the floor fit and objects."""
    sub = scene.subset(split.capture_idx)
    return replace(sub, depth_refined=None, points=None, floor=None, objects=[])


def refine_capture(capture_scene: Scene, out_dir: Path) -> Scene:
    """``capture_scene`` with refined depth computed from its own frames only (resumable file
    ``refined_capture-<key>.npy`` in ``out_dir``)."""

    key = hashlib.sha1(json.dumps(capture_scene.frame_ids).encode()).hexdigest()[:12]
    path = Path(out_dir) / f"refined_capture-{key}.npy"
    if not path.exists():
        refine_frames_to_file(capture_scene, path, desc="refine capture")
    return replace(capture_scene, depth_refined=np.load(path, mmap_mode="r"))


def _resize(color: np.ndarray, depth: np.ndarray, size_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    if color.shape[1::-1] == tuple(size_wh):
        return color, depth.astype(np.float32)
    return (cv2.resize(color, size_wh, interpolation=cv2.INTER_AREA),
            cv2.resize(depth.astype(np.float32), size_wh, interpolation=cv2.INTER_NEAREST))


def _up_from_poses(T_world_cam: np.ndarray) -> np.ndarray:
    """World 'up' estimated from camera poses only: minus the mean camera y axis (OpenCV y points
    down in the image, so a roughly upright camera's -y is up)."""
    up = -T_world_cam[:, :3, 1].mean(axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])


@dataclass
class TrainingSet:
    """All a training arm may see: built from the capture sub-scene only."""

    capture_scene: Scene
    """The capture frames (the renderer's scene)."""
    real_rgb: np.ndarray
    """uint8 (C, H, W, 3) capture images at the model size."""
    real_depth: np.ndarray
    """float32 (C, H, W) capture labels (0 = no label): the renderer's depth at the capture pose or
    the sensor depth (``DepthExperimentConfig.real_labels``)."""
    synth_poses: np.ndarray
    """(M, 4, 4) poses of the synthesized views."""
    synth_rgb: np.ndarray
    """uint8 (M, H, W, 3) synthesized images (holes filled, as a user would get them)."""
    synth_depth: np.ndarray
    """float32 (M, H, W) synthesized depth where synthesized, 0 where filled (no label)."""
    synth_seconds: float
    """Wall time of rendering the M views (and the C capture-pose labels when rendered)."""
    synth_cpu_seconds: float = float("nan")
    """CPU time (all threads of this process) of the same rendering."""
    sensor_depth: np.ndarray | None = None
    """float32 (C, H, W) the capture's sensor depth at the model size (for the label-density report)."""


def _render_views(renderer: Renderer, poses: np.ndarray, K, W: int, H: int, desc: str):
    rgb = np.zeros((len(poses), H, W, 3), np.uint8)
    dep = np.zeros((len(poses), H, W), np.float32)
    chunk = 16
    for a in progress(range(0, len(poses), chunk), desc=desc, unit="chunk"):
        for k, r in enumerate(renderer.render_batch(poses[a:a + chunk], K)):
            rgb[a + k] = r.color
            dep[a + k] = np.where(r.valid, r.depth_m, 0.0)
    return rgb, dep


def build_training_set(capture_scene: Scene, cfg: DepthExperimentConfig, cache: Path | None = None,
                       render_config: RenderConfig = RenderConfig()) -> TrainingSet:
    """Capture images/labels and M synthesized views from ``capture_scene`` (nothing else)."""
    W, H = cfg.size_wh
    rgb, dep = [], []
    for i in range(len(capture_scene)):
        f = capture_scene.frame(i, refined=True)  # refined only when refine_capture added it
        c, d = _resize(f.color, f.depth_m, (W, H))
        rgb.append(c)
        dep.append(d)
    real_rgb, sensor = np.stack(rgb), np.stack(dep)
    if not (sensor > 0).any():
        raise ValueError("the scene's capture frames have no depth (all zero): nothing to train or "
                         "render from")
    poses = synth_poses(capture_scene.T_world_cam, cfg.synth, cfg.pose_seed,
                        _up_from_poses(capture_scene.T_world_cam), cfg.poses)
    rendered_labels = cfg.real_labels == "rendered"
    key = hashlib.sha1(json.dumps([capture_scene.frame_ids, poses.round(9).tolist(), [W, H],
                                   capture_scene.depth_refined is not None, asdict(render_config),
                                   rendered_labels,
                                   np.asarray(capture_scene.T_world_cam).round(9).tolist()],
                                  default=str).encode()).hexdigest()[:16]
    if cache is not None and cache.exists():
        z = np.load(cache)
        if str(z["key"]) == key:
            real = z["real_label"] if rendered_labels else sensor
            return TrainingSet(capture_scene, real_rgb, real, poses, z["rgb"], z["depth"],
                               float(z["seconds"]), float(z["cpu_seconds"]), sensor)
    K = capture_scene.intrinsics[0].scaled(W, H)
    renderer = Renderer(capture_scene, render_config)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        s_rgb, s_dep = _render_views(renderer, poses, K, W, H, "synthesize")
        real = sensor
        if rendered_labels:
            _, real = _render_views(renderer, np.asarray(capture_scene.T_world_cam, np.float64), K, W, H,
                                    "capture labels")
    finally:
        renderer.close()
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    if cache is not None:
        buf = io.BytesIO()
        np.savez(buf, key=np.array(key), rgb=s_rgb, depth=s_dep, real_label=real, seconds=np.array(secs),
                 cpu_seconds=np.array(cpu))
        atomic_write_bytes(cache, buf.getvalue())
    return TrainingSet(capture_scene, real_rgb, real, poses, s_rgb, s_dep, secs, cpu, sensor)


@dataclass
class TestSet:
    """Real test frames at the model size (sensor depth as ground truth)."""

    rgb: np.ndarray
    depth: np.ndarray
    bin_of: np.ndarray
    example_rows: np.ndarray
    """Rows shown in the example figure: the median-distance frame of each bin."""
    dist: np.ndarray | None = None
    """(T,) combined pose distance of each test frame to the capture (``CaptureSplit.dist``)."""


RELEASE_EVERY = 16
"""Frames read between two :func:`release_frames` calls while streaming the test frames."""


def load_test_set(scene: Scene, split: CaptureSplit, size_wh: tuple[int, int]) -> TestSet:
    """The test frames' images and sensor depth. Used only to measure the trained models.

    Streams: each frame is read, resized into the preallocated model-size arrays, and the source's
    resident pages are dropped every :data:`RELEASE_EVERY` frames, so memory holds the model-size
    test set, not the full-size frames (a memory-mapped scene of 1000 VGA frames is ~2 GB)."""
    W, H = size_wh
    n = len(split.test_idx)
    rgb = np.empty((n, H, W, 3), np.uint8)
    depth = np.empty((n, H, W), np.float32)
    for k, i in enumerate(split.test_idx):
        c, d = scene.frames.load(int(i))
        rgb[k], depth[k] = _resize(c, d, size_wh)
        if k % RELEASE_EVERY == RELEASE_EVERY - 1:
            release_frames(scene.frames)
    release_frames(scene.frames)
    if not (depth > 0).any():
        raise ValueError("the scene's test frames have no valid sensor depth: nothing to test against")
    ex = []
    for b in range(len(BINS)):
        rows = np.flatnonzero(split.bin_of == b)
        ex.append(rows[np.argsort(split.dist[rows], kind="stable")[len(rows) // 2]])
    return TestSet(rgb, depth, split.bin_of, np.array(ex), split.dist)


def _pool(rgb: np.ndarray, depth: np.ndarray, device):
    """Images (2N, H, W, 3) uint8 and labels (2N, 1, H, W) float32 on ``device``: rows 0..N-1 as
    given, rows N..2N-1 flipped left-right (a flipped sample is row i + N). Images stay uint8 (a
    quarter of the memory of floats); :func:`_as_input` converts each batch."""
    import torch

    rgb2 = np.concatenate([rgb, rgb[:, :, ::-1]])
    dep2 = np.concatenate([depth, depth[:, :, ::-1]])
    x = torch.from_numpy(np.ascontiguousarray(rgb2)).to(device)
    y = torch.from_numpy(np.ascontiguousarray(dep2, dtype=np.float32)).to(device)[:, None]
    return x, y


def _as_input(rgb_u8):
    """uint8 (B, H, W, 3) tensor -> float (B, 3, H, W) in [0, 1], channels-last memory."""
    import torch

    return rgb_u8.permute(0, 3, 1, 2).float().div_(255.0).contiguous(memory_format=torch.channels_last)


def batch_rows(arm: str, seed: int, n_real: int, n_synth: int, cfg: DepthExperimentConfig) -> np.ndarray:
    """(steps, B) rows into the pool ``[real, real flipped, synth, synth flipped]`` for every step of
    one arm and seed, drawn up front from two seeded streams shared by all arms (so ``capture`` and
    ``capture+synth`` see the same real samples and flips at every step; ``capture+synth``'s batch
    is ``capture``'s plus ``synth``'s)."""
    rng_real, rng_syn = np.random.default_rng([seed, 1]), np.random.default_rng([seed, 2])
    ri = rng_real.integers(0, n_real, (cfg.steps, cfg.batch_real))
    ri = ri + n_real * (rng_real.random((cfg.steps, cfg.batch_real)) < 0.5)
    si = rng_syn.integers(0, n_synth, (cfg.steps, cfg.batch_synth))
    si = si + n_synth * (rng_syn.random((cfg.steps, cfg.batch_synth)) < 0.5) + 2 * n_real
    parts = ([ri] if arm != "synth" else []) + ([si] if arm != "capture" else [])
    return np.concatenate(parts, axis=1)


def _predict(net, rgb: np.ndarray, device, batch: int = 32) -> np.ndarray:
    import torch

    net.eval()
    out = []
    with torch.no_grad():
        for a in range(0, len(rgb), batch):
            out.append(net(_as_input(torch.from_numpy(rgb[a:a + batch]).to(device)))[:, 0].cpu().numpy())
    net.train()
    return np.concatenate(out)


def _evaluate(pred: np.ndarray, test: TestSet, max_depth_m: float) -> dict:
    """Pooled metrics overall and per bin, plus each test frame's squared-error sum and pixel count
    (``per_frame``: any other binning of the test frames pools these)."""
    overall = DepthErrorSums()
    per = {b: DepthErrorSums() for b in BINS}
    sq, n = [], []
    for k in range(len(pred)):
        f = DepthErrorSums()
        f.add(pred[k], test.depth[k], max_depth_m=max_depth_m)
        overall.merge(f)
        per[BINS[test.bin_of[k]]].merge(f)
        sq.append(f.sq)
        n.append(f.n)
    return {"overall": overall.result(), "bins": {b: s.result() for b, s in per.items()},
            "per_frame": {"sq_sum": sq, "n_pixels": n}}


def train_arm(arm: str, seed: int, data: TrainingSet, test: TestSet,
              cfg: DepthExperimentConfig) -> tuple[dict, np.ndarray]:
    """Train one arm with one seed; returns (result dict, example predictions (3, H, W))."""
    import torch

    from presim.evaluation.sim2real.model import DepthNet, depth_loss  # imports torch (optional)

    if arm not in ARMS:
        raise ValueError(f"arm must be one of {ARMS}, got {arm!r}")
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available here")
    device = torch.device(cfg.device)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(seed)  # same initial weights for every arm of a seed
    net = DepthNet(cfg.width, cfg.max_depth_m).to(device).to(memory_format=torch.channels_last)
    try:
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, fused=True)
    except (RuntimeError, TypeError, ValueError):  # no fused Adam for this device/build
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: lr_factor(k, cfg))
    # Every sample of every step is decided before training: one pool tensor on the device, one
    # index tensor per step (no per-step numpy work or host copies).
    rx, ry = _pool(data.real_rgb, data.real_depth, device)
    sx, sy = _pool(data.synth_rgb, data.synth_depth, device)
    pool_x, pool_y = torch.cat([rx, sx]), torch.cat([ry, sy])
    del rx, sx, ry, sy
    rows = torch.from_numpy(batch_rows(arm, seed, len(data.real_rgb), len(data.synth_rgb), cfg)).to(device)
    checkpoints = sorted({int(round(s)) for s in np.linspace(0, cfg.steps, cfg.eval_points + 1)[1:]})
    losses = torch.zeros(cfg.steps, dtype=torch.float64)
    curve = []
    t0, c0 = time.perf_counter(), time.process_time()
    for step in progress(range(1, cfg.steps + 1), desc=f"{arm} seed {seed}", unit="step"):
        r = rows[step - 1]
        loss = depth_loss(net(_as_input(pool_x.index_select(0, r))), pool_y.index_select(0, r))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses[step - 1] = loss.detach().to("cpu", torch.float64)
        if step in checkpoints and step != cfg.steps:  # the last model is measured below
            m = _evaluate(_predict(net, test.rgb, device), test, cfg.max_depth_m)
            curve.append({"step": step, "rms": m["overall"]["rms"], "lr": opt.param_groups[0]["lr"],
                          **{f"rms_{b}": m["bins"][b]["rms"] for b in BINS}})
    train_s, train_cpu = time.perf_counter() - t0, time.process_time() - c0
    pred = _predict(net, test.rgb, device)
    metrics = _evaluate(pred, test, cfg.max_depth_m)
    if cfg.steps in checkpoints:
        curve.append({"step": cfg.steps, "rms": metrics["overall"]["rms"], "lr": opt.param_groups[0]["lr"],
                      **{f"rms_{b}": metrics["bins"][b]["rms"] for b in BINS}})
    result = {"arm": arm, "seed": seed, **metrics, "train_loss": losses.tolist(), "test_curve": curve,
              "train_seconds": train_s, "train_cpu_seconds": train_cpu, "steps": cfg.steps}
    return result, pred[test.example_rows]


def _mean_std(vals: list[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (None with a single seed: no spread was measured)."""
    a = np.asarray(vals, np.float64)
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else None


def _aggregate(runs: list[dict]) -> dict:
    out: dict = {}
    for key in ("rms", "absrel", "delta1"):
        out[key], out[f"{key}_std"] = _mean_std([r["overall"][key] for r in runs])
    out["bins"] = {}
    for b in BINS:
        d = {}
        for key in ("rms", "absrel", "delta1"):
            d[key], d[f"{key}_std"] = _mean_std([r["bins"][b][key] for r in runs])
        out["bins"][b] = d
    out["seeds"] = {str(r["seed"]): {"overall": r["overall"], "bins": r["bins"]} for r in runs}
    out["train_seconds"] = [r["train_seconds"] for r in runs]
    return out


class ExperimentMismatch(ValueError):
    """DIR holds results of another configuration, scene or code version."""


_RESULT_FILES = ("summary.json", "report.md", "learning_curves.png", "examples.png", "timing.json",
                 "rms_vs_distance.png")


def _claim_dir(out: Path, cfg: DepthExperimentConfig, fp: str, restart: bool) -> None:
    """Record the fingerprint in DIR/experiment.json; refuse a DIR made with another one (or, with
    ``restart``, delete its results first)."""
    marker = out / "experiment.json"
    if marker.exists():
        try:
            old = json.loads(marker.read_text()).get("fingerprint")
        except (json.JSONDecodeError, AttributeError):
            old = None
        if old != fp:
            if not restart:
                raise ExperimentMismatch(
                    f"{out}: holds results of another configuration, scene or code version (fingerprint "
                    f"{old} vs {fp}); use a new --out, or --restart to delete them")
            shutil.rmtree(out / "runs", ignore_errors=True)
            for f in _RESULT_FILES:
                (out / f).unlink(missing_ok=True)
    elif restart:
        shutil.rmtree(out / "runs", ignore_errors=True)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    d = asdict(cfg)
    d.pop("seeds")
    d.pop("threads")
    atomic_write_json(marker, {"fingerprint": fp, "code": code_version(), "config": d})


def run_depth_experiment(scene: Scene, cfg: DepthExperimentConfig, out_dir: str | Path,
                         scene_label: str = "", restart: bool = False) -> dict:
    """Run (or resume) all arms and seeds and write DIR/summary.json, report.md, learning_curves.png,
    examples.png. Returns the summary.

    A DIR made with another fingerprint (settings but seeds/threads, scene and poses, code version)
    raises :class:`ExperimentMismatch`; ``restart=True`` deletes its results and starts over (the
    rendered-view cache has its own key and is reused when it still matches)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fp = cfg.fingerprint(scene)
    _claim_dir(out, cfg, fp, restart)
    t_all, c_all, load0 = time.perf_counter(), time.process_time(), os.getloadavg()
    split = split_capture(scene.T_world_cam, cfg.capture_every)
    sub = capture_subscene(scene, split)
    if cfg.refine:
        sub = refine_capture(sub, out)
    data = build_training_set(sub, cfg, cache=out / "synth.npz")
    test = load_test_set(scene, split, cfg.size_wh)
    runs: dict[str, list[dict]] = {a: [] for a in ARMS}
    examples: dict[str, np.ndarray] = {}
    for seed in cfg.seeds:
        for arm in ARMS:
            base = out / "runs" / f"{_ARM_FILE[arm]}-seed{seed}"
            js, npz = base.with_suffix(".json"), base.with_suffix(".npz")
            res = None
            if js.exists() and npz.exists():
                res = json.loads(js.read_text())
                if res.get("fingerprint") != fp:  # cannot happen after _claim_dir unless edited by hand
                    raise ExperimentMismatch(f"{js}: made with another fingerprint than {fp}; use --restart")
            if res is None:
                res, ex = train_arm(arm, seed, data, test, cfg)
                res["fingerprint"] = fp
                buf = io.BytesIO()
                np.save(buf, ex.astype(np.float32))
                atomic_write_bytes(npz, buf.getvalue())
                atomic_write_json(js, res, indent=None)  # written last: marks the run complete
            runs[arm].append(res)
            if seed == cfg.seeds[0]:
                examples[arm] = np.load(npz)
    bins = split.bin_summary()
    bins["edges"] = {"near_mid": split.bin_edges[0], "mid_far": split.bin_edges[1],
                     "distance": "t / 0.10 m + r / 10 deg to the nearest capture frame; bins = terciles"}
    config = asdict(cfg)
    config.update({"recipe": recipe_name(cfg), "scene": scene_label or str(scene.path or scene.meta.source), "n_frames": len(scene),
                   "n_capture": int(len(split.capture_idx)), "n_test": int(len(split.test_idx)),
                   "synth_valid_frac": float((data.synth_depth > 0).mean()),
                   "real_valid_frac": float((data.real_depth > 0).mean()),
                   "sensor_valid_frac": (float((data.sensor_depth > 0).mean())
                                         if data.sensor_depth is not None else None),
                   "poses": getattr(scene, "poses_source", "given"), "code": code_version(),
                   "labels": ("capture: " + ("the renderer's depth at each capture pose where synthesized"
                                             if cfg.real_labels == "rendered" else "the depth") + " of the "
                              f"capture frames' {'refined (capture-only references)' if cfg.refine else 'sensor'} "
                              "depth; synth: rendered depth where synthesized (filled pixels unlabelled) from "
                              "the same depth; test: sensor depth"),
                   "metrics": "pooled over valid test pixels (0 < gt <= max_depth_m) at the model size"})
    summary = {"arms": {a: _aggregate(runs[a]) for a in ARMS}, "bins": bins, "config": config,
               "distance_curve": distance_curve(runs, test.dist)}
    timing = {"synthesize_s": data.synth_seconds, "synthesize_cpu_s": data.synth_cpu_seconds,
              "synth_views": cfg.synth,
              "train_s": {a: [r["train_seconds"] for r in runs[a]] for a in ARMS},
              "train_cpu_s": {a: [r.get("train_cpu_seconds") for r in runs[a]] for a in ARMS},
              "this_invocation_s": time.perf_counter() - t_all,
              "this_invocation_cpu_s": time.process_time() - c_all,
              "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg())}
    write_figures(out, summary, runs, examples, test, cfg.steps, cfg.seeds, cfg.max_depth_m)
    atomic_write_json(out / "timing.json", timing)
    atomic_write_text(out / "report.md", report_markdown(summary, timing))
    atomic_write_json(out / "summary.json", summary)
    return summary
