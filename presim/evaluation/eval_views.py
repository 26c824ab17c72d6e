"""Leave-one-out evaluation of view synthesis (thesis §3.5) with the thesis ablations and a TSDF-mesh
baseline.

Protocol: the *capture* is every ``stride``-th frame of the scene (by position); the *targets* are the
capture frames whose position in the capture is a positive multiple of ``target_every``. Each target
is rendered from the other capture frames (``Scene.subset`` without it) at its own pose and
intrinsics and compared with the real image. Every method gets the same final hole filling.

The refined depth of the capture frames is computed once, with only capture frames as references,
and cached (``<cache_dir>/refined_<hash>.npy``; the target's color is thus one of the references
when its neighbours' depth is refined; the depth of the target itself is never used to render it).
The refined depth is then completed (:mod:`presim.depth.complete`, ``EvalConfig.complete``; its
multi-view check reads no target) and cached beside it (``completed_<hash>.npy``).

Metrics per method (means over targets):
- ``psnr_db``: PSNR of the delivered (filled) color image vs the real image.
- ``psnr_black_db``: PSNR with pixels no view covered set to black (no filling).
- ``psnr_covered_db``: PSNR over synthesized (covered) pixels only.
- ``psnr_hole_db``: PSNR of the delivered image over the hole pixels alone (no view covered them,
  the fill made them); NaN for a target without holes, and the mean is over targets with holes.
- ``ssim``: SSIM (scikit-image, RGB, data range 255) of the delivered image.
- ``hole_frac``: fraction of pixels no view covered, before filling.
- ``psnr_nodepth_db`` / ``nodepth_frac``: PSNR over, and fraction of, the pixels no *measured* depth
  covered (those the completion stage covered plus the holes): the hole pixels of the same method
  without completion, so its gain there is compared on the same pixels.
- ``depth_absrel``: mean |d - d_real| / d_real over covered pixels where the real depth is valid.
- ``ms_per_frame``: wall time of one steady-state render (after a warm-up render of the same pose),
  filling included; per-scene preparation (renderer construction, TSDF fusion) excluded.

Every metric is taken over the target's valid pixels (``image_metrics(real_valid=...)``; a scene
carries no per-pixel validity mask today, the importers crop undistorted frames to their valid
rectangle, so eval-views scores every pixel). ``images_dir`` adds pictures: one strip per target and
method and ``report.md`` (:mod:`presim.evaluation.report`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from presim.capture.scene import Scene
from presim.depth.complete import CompleteConfig, complete_scene_depth
from presim.depth.filters import guided_filter_depth, median_filter_depth
from presim.depth.fuse import FuseConfig
from presim.depth.refine import RefineConfig
from presim.depth.scene_fuse import fuse_frames
from presim.depth.scene_refine import refine_frames_to_file, refine_one_frame
from presim.evaluation.report import eval_strip, strip_name, write_report
from presim.evaluation.smooth_fit import SmoothFitConfig, fit_smoothing
from presim.evaluation.tsdf_baseline import MeshRaycaster, TSDFConfig, fuse_tsdf_mesh
from presim.io_utils import progress, write_npy_atomic, write_png
from presim.photometric import PhotometricConfig, calibrate_photometric
from presim.synthesis.fill import fill_holes
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.sensors.rgbd import RGBD

__all__ = ["METHODS", "DEFAULT_METHODS", "EvalConfig", "EvalResult", "eval_views", "format_table", "uses_fitted_filter",
           "capture_and_targets", "image_metrics"]

TARGET_EXPOSURE = "<target>"
"""``exposure_frame`` override meaning "the frame id of the target being rendered"."""

# Method name -> (RenderConfig overrides, depth variant). Depth variant: "refined" (the scene's
# refinement), "raw" (sensor depth), "guided" / "median" (filters of the raw depth used in place of
# the refinement), "fused" (sensor depth aligned to and fused with the refinement, thesis §5.3.4,
# presim.depth.scene_fuse), or "tsdf" (the mesh baseline, no Renderer).
# "full" is the best measured combination (photometric correction matched to the target's
# exposure + sharpness-aware views + blending of 6 views; docs/evaluation.md); "thesis" is the
# thesis pipeline (RenderConfig() defaults but the thesis's adaptive loop, min_view_gain = 0);
# "default" is RenderConfig() as it is (what `presim render` and the simulator use: the loop stops
# at diminishing returns, docs/synthesis.md). Every other method keeps the thesis's loop too
# (THESIS_LOOP), so each one measures the algorithm it names, not the stop.
THESIS_LOOP: dict = {"min_view_gain": 0.0}
BEST: dict = {"use_photometric": True, "exposure_frame": TARGET_EXPOSURE, "sharpness": True, "blend": True, "blend_views": 6}
METHODS: dict[str, tuple[dict, str]] = {
    "full": (BEST, "refined"),
    "thesis": ({}, "refined"),
    "default": ({}, "refined"),
    # the default with backward colour sampling (colours read in the source images)
    "default_backward": ({"backward_color": True}, "refined"),
    # the default on the capture calibrated by `presim photometric` (predicted exposure)
    "default_photo": ({"use_photometric": True}, "refined"),
    # candidates for the default (the default's loop): blending of 6 views, with sharpness weighting
    "default_blend6": ({"blend": True, "blend_views": 6, "backward_color": True}, "refined"),
    "default_fill_bg": ({"fill_background_px": 4}, "refined"),
    # the default without the reconstruction filter fitted on the capture (presim.evaluation.smooth_fit)
    "default_nosmooth": ({"smooth_sigma_px": 0.0}, "refined"),
    # the default without the capture's completed depth (presim.depth.complete)
    "default_nocomplete": ({"use_completed_depth": False}, "refined"),
    # neither: the renderer's default on a scene with no completed depth and no fitted filter
    "default_nocomplete_nosmooth": ({"use_completed_depth": False, "smooth_sigma_px": 0.0}, "refined"),
    # the default without the ring of further views for big holes (RenderConfig.hole_candidates)
    "default_local": ({"hole_candidates": 0}, "refined"),
    # the default before completion, filter and ring: identical to 76d1f55's default on the shared captures
    "default_before": ({"use_completed_depth": False, "smooth_sigma_px": 0.0, "hole_candidates": 0}, "refined"),
    "default_blend6_photo": ({"blend": True, "blend_views": 6, "backward_color": True, "use_photometric": True},
                             "refined"),
    "DIBR": ({"num_layers": 1}, "raw"),
    "DIBR_DR": ({"num_layers": 1}, "refined"),
    "LDIBR": ({}, "raw"),
    "LDIBR_DR": ({}, "refined"),
    "sel_distance": ({"selection": "distance"}, "refined"),
    "sel_angle": ({"selection": "angle"}, "refined"),
    "fixed_1": ({"fixed_views": 1}, "refined"),
    "fixed_2": ({"fixed_views": 2}, "refined"),
    "fixed_3": ({"fixed_views": 3}, "refined"),
    "median_plain": ({"crack_filter": "median"}, "refined"),
    "depth_guided": ({}, "guided"),
    "depth_median": ({}, "median"),
    **{f"layers_{k}": ({"num_layers": k}, "refined") for k in range(1, 9)},
    "tsdf_mesh": ({}, "tsdf"),
    # Beyond the thesis. Photometric methods use a calibration of the capture
    # (presim.photometric, refined depth); exposure_frame "<target>" = the target's own.
    "photo": ({"use_photometric": True, "exposure_frame": TARGET_EXPOSURE}, "refined"),
    "photo_mean": ({"use_photometric": True, "predict_exposure": False}, "refined"),
    # exposure predicted from the views near the pose (no information from the target)
    "photo_pred": ({"use_photometric": True}, "refined"),
    # The same with the other colour models of `presim photometric` (the "photometric_*" keys pick
    # the calibration, not a RenderConfig field).
    "photo_affine": ({"use_photometric": True, "exposure_frame": TARGET_EXPOSURE, "photometric_model": "affine"},
                     "refined"),
    "photo_vig": ({"use_photometric": True, "exposure_frame": TARGET_EXPOSURE, "photometric_vignetting": True},
                  "refined"),
    "photo_affine_vig": ({"use_photometric": True, "exposure_frame": TARGET_EXPOSURE, "photometric_model": "affine",
                          "photometric_vignetting": True}, "refined"),
    "blend": ({"blend": True}, "refined"),
    "blend_2": ({"blend": True, "blend_views": 2}, "refined"),
    "blend_6": ({"blend": True, "blend_views": 6}, "refined"),
    "photo_blend": ({"blend": True, "use_photometric": True, "exposure_frame": TARGET_EXPOSURE}, "refined"),
    "sharp": ({"sharpness": True}, "refined"),
    "sharp_blend": ({"sharpness": True, "blend": True}, "refined"),
    "photo_sharp_blend": ({"sharpness": True, "blend": True, "use_photometric": True,
                           "exposure_frame": TARGET_EXPOSURE}, "refined"),
    "photo_sharp_blend_6": (BEST, "refined"),
    # Depth alignment + fusion (§5.3.4) in place of the refined depth.
    "fused": ({}, "fused"),
    "full_fused": (BEST, "fused"),
    "fused_est": ({}, "fused_est"),  # fusion taking the refined value where both agree
}
DEFAULT_METHODS = tuple(m for m in METHODS if not m.startswith("photo_affine") and m != "photo_vig")
"""Every method but the colour-model variants of ``photo`` (each needs its own calibration)."""
METRICS = ("psnr_db", "psnr_black_db", "psnr_covered_db", "psnr_hole_db", "ssim", "hole_frac", "psnr_nodepth_db",
           "nodepth_frac", "depth_absrel", "ms_per_frame")


@dataclass(frozen=True)
class EvalConfig:
    """Protocol of ``presim eval-views``."""

    stride: int = 1
    """Capture = every ``stride``-th frame of the scene."""
    target_every: int = 5
    """Targets = capture frames at capture positions that are positive multiples of this."""
    methods: tuple[str, ...] = DEFAULT_METHODS
    """Methods to evaluate (keys of :data:`METHODS`)."""
    max_targets: int | None = None
    """Evaluate at most this many targets (evenly spread over the eligible ones)."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Refinement used for the capture frames."""
    refine_workers: int = 1
    """Processes for the (cached) refinement of the capture frames."""
    tsdf_voxel_m: float | None = None
    """TSDF voxel size; None = 1/250 of the capture's median depth range, clamped to [4 mm, 2 cm]."""
    warmup: bool = True
    """Render each target once before the timed render (steady-state timing)."""
    complete: CompleteConfig | None = field(default_factory=CompleteConfig)
    """Depth completion of the capture (:mod:`presim.depth.complete`); None = none (methods then render
    as on a scene without completed depth)."""
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    """Photometric calibration of the capture (methods with ``use_photometric``)."""
    smooth: SmoothFitConfig | None = field(default_factory=SmoothFitConfig)
    """Reconstruction filter fitted on the capture's non-target frames, used by the methods named
    ``default*`` and ``full*`` (:func:`uses_fitted_filter`); None = no filter for any method."""


@dataclass(frozen=True)
class EvalResult:
    """Per-method mean metrics plus per-target values."""

    methods: dict[str, dict[str, float]]
    per_target: dict[str, list[dict[str, float]]]
    target_ids: list[str]
    skipped: dict[str, str]
    refine_s: float

    def to_json(self) -> dict:
        return {"methods": self.methods, "skipped": self.skipped, "targets": self.target_ids,
                "per_target": self.per_target, "refine_s": self.refine_s}


def uses_fitted_filter(method: str) -> bool:
    """Whether ``method`` renders with the filter fitted on the capture, as the renderer's default does on a
    scene with ``render_filter.json``; the thesis and its ablations are measured without it."""
    return method.startswith(("default", "full"))


def capture_and_targets(num_frames: int, stride: int, target_every: int) -> tuple[list[int], list[int]]:
    """(capture frame positions in the scene, target positions *within the capture*)."""
    if stride < 1 or target_every < 1:
        raise ValueError(f"stride and target_every must be >= 1, got {stride}, {target_every}")
    capture = list(range(0, num_frames, stride))
    targets = [k for k in range(len(capture)) if k > 0 and k % target_every == 0]
    return capture, targets


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    if mask is not None:
        if not mask.any():
            return float("nan")
        a, b = a[mask], b[mask]
    mse = float(np.mean((a - b) ** 2))
    return 100.0 if mse <= 1e-12 else float(10.0 * np.log10(255.0 ** 2 / mse))


_SSIM_PAD = 3
"""Border skimage's SSIM mean leaves out: (win_size - 1) // 2 with its default 7x7 window."""


def image_metrics(out: RGBD, real_color: np.ndarray, real_depth_m: np.ndarray,
                  unfilled_color: np.ndarray | None = None, real_valid: np.ndarray | None = None,
                  completed: np.ndarray | None = None) -> dict[str, float]:
    """Metrics of one rendered target (see module docstring); ``ms_per_frame`` is added by the caller.

    ``out.valid`` is the coverage: False = a hole (no view covered the pixel; filled in ``out.color``).
    ``real_valid`` (bool (H, W), None = all) marks the pixels where the real image has data; every
    metric ignores the others (SSIM: the mean of its map over them; ``hole_frac``: holes among them).
    ``completed`` (bool (H, W)): pixels covered by completed depth; ``psnr_nodepth_db`` / ``nodepth_frac``
    are then on the pixels no *measured* depth covered (the holes of the same render without completion).
    """
    from skimage.metrics import structural_similarity

    valid = np.asarray(out.valid, dtype=bool)
    rv = None if real_valid is None else np.asarray(real_valid, dtype=bool)
    if rv is not None and rv.shape != valid.shape:
        raise ValueError(f"image_metrics: real_valid shape {rv.shape} != image {valid.shape}")
    covered = valid if rv is None else valid & rv
    holes = ~valid if rv is None else ~valid & rv
    black = (unfilled_color if unfilled_color is not None else out.color).copy()
    black[~valid] = 0
    m = covered & (real_depth_m > 0) & (out.depth_m > 0)
    absrel = float(np.mean(np.abs(out.depth_m[m] - real_depth_m[m]) / real_depth_m[m])) if m.any() else float("nan")
    if rv is None:
        ssim = float(structural_similarity(out.color, real_color, channel_axis=2, data_range=255))
        hole_frac = float(out.hole_frac_before_fill)
    else:
        _, smap = structural_similarity(out.color, real_color, channel_axis=2, data_range=255, full=True)
        inner = np.zeros_like(rv)  # skimage's mean leaves out a border of half its 7x7 window
        inner[_SSIM_PAD:-_SSIM_PAD, _SSIM_PAD:-_SSIM_PAD] = rv[_SSIM_PAD:-_SSIM_PAD, _SSIM_PAD:-_SSIM_PAD]
        ssim = float(smap.mean(axis=2)[inner].mean()) if inner.any() else float("nan")
        hole_frac = float(holes.sum() / rv.sum()) if rv.any() else float("nan")
    nodepth = holes if completed is None else holes | (completed if rv is None else completed & rv)
    return {
        "psnr_db": _psnr(out.color, real_color, rv),
        "psnr_black_db": _psnr(black, real_color, rv),
        "psnr_covered_db": _psnr(out.color, real_color, covered),
        "psnr_hole_db": _psnr(out.color, real_color, holes),
        "ssim": ssim,
        "hole_frac": hole_frac,
        "psnr_nodepth_db": _psnr(out.color, real_color, nodepth),
        "nodepth_frac": float(nodepth.sum() / (nodepth.size if rv is None else max(rv.sum(), 1))),
        "depth_absrel": absrel,
    }


def _photometric_key(overrides: dict, base) -> tuple[str, bool]:
    """(model, vignetting) of the photometric calibration a method uses."""
    return (overrides.get("photometric_model", base.model),
            bool(overrides.get("photometric_vignetting", base.vignetting)))


def _render_config(overrides: dict, use_refined: bool, thesis_loop: bool = True):
    names = {f.name for f in dataclasses.fields(RenderConfig)}
    missing = [k for k in overrides if k not in names]
    if missing:
        return None, f"RenderConfig has no field(s) {missing}"
    kw = {**THESIS_LOOP, **overrides} if thesis_loop else dict(overrides)
    if "use_refined_depth" in names:
        kw["use_refined_depth"] = use_refined
    if "fill_holes" in names:
        kw["fill_holes"] = True
    return RenderConfig(**kw), ""


def _fill(color: np.ndarray, depth_m: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The renderer's final hole filling (same for every method)."""
    return fill_holes(color, depth_m, valid)


def _refined_capture_depth(scene: Scene, capture: list[int], cfg: EvalConfig,
                           cache_dir: Path | None) -> np.ndarray:
    if cache_dir is None and scene.path is not None:
        cache_dir = Path(scene.path) / "eval_cache"
    if cache_dir is None:
        sub = scene.subset(capture)
        pool = list(range(len(capture)))
        return np.stack([refine_one_frame(sub, k, pool, cfg.refine) for k in
                         progress(range(len(capture)), desc="refine capture", unit="frame")])
    key = {"refine": _refine_key(cfg.refine), "capture": capture,
           "frames": list(scene.frame_ids), "src": str(scene.path)}
    if scene.poses_source != "given":  # refined depth depends on the poses (given keys stay as before)
        key["poses"] = hashlib.sha256(np.ascontiguousarray(scene.T_world_cam).tobytes()).hexdigest()[:16]
    key = json.dumps(key, sort_keys=True)
    out = Path(cache_dir) / f"refined_{hashlib.sha256(key.encode()).hexdigest()[:16]}.npy"
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        refine_frames_to_file(scene, out, indices=capture, ref_pool=capture, config=cfg.refine,
                              workers=cfg.refine_workers if scene.path is not None else 1,
                              desc="refine capture")
    arr = np.load(out, mmap_mode="r")
    if arr.shape != (len(capture), scene.height, scene.width):
        raise ValueError(f"{out}: cached refinement has shape {arr.shape}, expected "
                         f"{(len(capture), scene.height, scene.width)}; delete it")
    return arr


def _completed_capture_depth(cap: Scene, refined: np.ndarray, pool: list[int], complete: CompleteConfig,
                             cache_dir: Path | None, scene: Scene) -> np.ndarray:
    """The capture's completed depth (:mod:`presim.depth.complete`) on its refined depth, cached beside
    the refinement."""
    sub = dataclasses.replace(cap, depth_refined=refined)
    if cache_dir is None and scene.path is not None:
        cache_dir = Path(scene.path) / "eval_cache"
    if cache_dir is None:
        return complete_scene_depth(sub, config=complete, pool=pool, desc="complete capture depth")
    key = json.dumps({"complete": dataclasses.asdict(complete), "pool": pool, "frames": list(cap.frame_ids),
                      "refined": hashlib.sha256(np.ascontiguousarray(refined[::7]).tobytes()).hexdigest()[:16],
                      "poses": hashlib.sha256(np.ascontiguousarray(cap.T_world_cam).tobytes()).hexdigest()[:16]},
                     sort_keys=True)
    out = Path(cache_dir) / f"completed_{hashlib.sha256(key.encode()).hexdigest()[:16]}.npy"
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        write_npy_atomic(out, np.float32, (len(cap), cap.height, cap.width),
                         lambda arr: complete_scene_depth(sub, config=complete, pool=pool, out=arr,
                                                          desc="complete capture depth"))
    return np.load(out, mmap_mode="r")


def _refine_key(refine: RefineConfig) -> dict:
    # As before the sharpness-reference fields existed while they are off (keeps existing caches).
    d = dataclasses.asdict(refine)
    if not d.get("sharp_refs"):
        d.pop("sharp_refs", None)
        d.pop("sharp_refs_gamma", None)
    return d


def _spread(items: list[int], n: int | None) -> list[int]:
    if n is None or n >= len(items):
        return items
    pos = np.linspace(0, len(items) - 1, max(n, 1)).round().astype(int)
    return [items[p] for p in sorted(set(pos.tolist()))]


def eval_views(scene: Scene, config: EvalConfig = EvalConfig(), cache_dir: str | Path | None = None,
               log: Callable[[str], None] | None = None, images_dir: str | Path | None = None,
               strip_width: int | None = None) -> EvalResult:
    """Run the leave-one-out evaluation (see module docstring) and return per-method metrics.

    ``images_dir``: also write one strip per target and method (``<target>_<method>.png``, panels
    ``strip_width`` pixels wide, None = the target's width) and ``report.md`` there
    (:mod:`presim.evaluation.report`).
    """
    unknown = [m for m in config.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; choose from {sorted(METHODS)}")
    capture, targets = capture_and_targets(len(scene), config.stride, config.target_every)
    targets = _spread(targets, config.max_targets)
    if not targets:
        raise ValueError(f"no targets: {len(capture)} capture frames (stride {config.stride}) and "
                         f"target_every {config.target_every} leave no capture position > 0 that is a multiple")
    variants = {METHODS[m][1] for m in config.methods}
    cap = scene.subset(capture)  # positions 0..M-1, depth_refined re-indexed lazily
    t0 = time.perf_counter()
    depth_sets: dict[str, np.ndarray | None] = {"raw": None}
    if variants & {"refined"}:
        depth_sets["refined"] = _refined_capture_depth(scene, capture, config,
                                                       None if cache_dir is None else Path(cache_dir))
    if variants & {"fused", "fused_est"}:
        if depth_sets.get("refined") is None:
            depth_sets["refined"] = _refined_capture_depth(scene, capture, config,
                                                           None if cache_dir is None else Path(cache_dir))
        t1 = time.perf_counter()
        for v, agree_value in (("fused", "sensor"), ("fused_est", "estimate")):
            if v in variants:
                depth_sets[v] = fuse_frames(cap, depth_sets["refined"], fuse=FuseConfig(agree_value=agree_value),
                                            desc="fuse capture depth")
        if log is not None:
            log(f"depth alignment + fusion of the capture: {(time.perf_counter() - t1) / len(cap) * 1e3:.0f} ms/frame")
    refine_s = time.perf_counter() - t0
    completed = None
    if depth_sets.get("refined") is not None and config.complete is not None:
        t1 = time.perf_counter()
        pool = [j for j in range(len(cap)) if j not in set(targets)]  # the check never reads a target
        completed = _completed_capture_depth(cap, depth_sets["refined"], pool, config.complete,
                                             None if cache_dir is None else Path(cache_dir), scene)
        if log is not None:
            log(f"depth completion of the capture: {(time.perf_counter() - t1) / len(cap) * 1e3:.0f} ms/frame, "
                f"{100 * float(np.mean([(completed[i] > 0).mean() for i in range(len(cap))])):.2f} % of pixels")
    fitted = None
    if config.smooth is not None and any(uses_fitted_filter(m) for m in config.methods):
        t1 = time.perf_counter()
        fit_scene = dataclasses.replace(cap, depth_refined=depth_sets.get("refined"), depth_completed=completed,
                                        photometric=None, render_filter_sigma_px=None)
        fit = fit_smoothing(fit_scene, config.smooth, exclude=targets)  # never renders or reads a target
        fitted = fit.sigma_px
        if log is not None:
            log(f"reconstruction filter fitted on {len(fit.frames)} capture frames: sigma {fitted:.1f} px "
                f"({time.perf_counter() - t1:.1f} s)")
    if "guided" in variants or "median" in variants:
        raws = [cap.frame(k) for k in range(len(cap))]
        if "guided" in variants:
            depth_sets["guided"] = np.stack([guided_filter_depth(f.color, f.depth_m) for f in raws])
        if "median" in variants:
            depth_sets["median"] = np.stack([median_filter_depth(f.depth_m) for f in raws])
        del raws
    photo_calibs: dict[tuple, object] = {}  # (model, vignetting) -> calibration of the capture
    for m in config.methods:
        ov = METHODS[m][0]
        key = _photometric_key(ov, config.photometric)
        if not ov.get("use_photometric") or key in photo_calibs:
            continue
        t1 = time.perf_counter()
        ref_cap = cap if depth_sets.get("refined") is None else dataclasses.replace(cap, depth_refined=depth_sets["refined"])
        pc = photo_calibs[key] = calibrate_photometric(
            ref_cap, dataclasses.replace(config.photometric, model=key[0], vignetting=key[1]))
        if log is not None:
            log(f"photometric calibration of the capture ({key[0]}{', vignetting' if key[1] else ''}): "
                f"{time.perf_counter() - t1:.1f} s, residual RMS {np.mean(pc.stats['rms_before']):.2f} -> "
                f"{np.mean(pc.stats['rms_after']):.2f} levels")
    if "tsdf" in variants:
        deps = np.stack([cap.depth(k, refined=False) for k in range(0, len(cap), max(1, len(cap) // 10))])
        med = float(np.median(deps[deps > 0])) if (deps > 0).any() else 1.0
        voxel = config.tsdf_voxel_m or float(np.clip(med / 250.0, 0.004, 0.02))

    per: dict[str, list[dict[str, float]]] = {m: [] for m in config.methods}
    skipped: dict[str, str] = {}
    for k in progress(targets, desc="targets", unit="view"):
        others = [j for j in range(len(cap)) if j != k]
        f = cap.frame(k)
        for name in config.methods:
            if name in skipped:
                continue
            overrides, variant = METHODS[name]
            if variant == "tsdf":
                mesh = fuse_tsdf_mesh(cap, others, TSDFConfig(voxel_m=voxel))
                caster = MeshRaycaster(mesh)
                if config.warmup:
                    caster.render(f.T_world_cam, f.K)
                t1 = time.perf_counter()
                color, depth, valid = caster.render(f.T_world_cam, f.K)
                fc, fd = _fill(color, depth, valid)
                ms = (time.perf_counter() - t1) * 1e3
                out = RGBD(fc, fd, valid, np.full(valid.shape, -1, np.int32), f.K, f.T_world_cam,
                           float(1.0 - valid.mean()))
                unfilled = color
            else:
                if overrides.get("exposure_frame") == TARGET_EXPOSURE:
                    overrides = {**overrides, "exposure_frame": cap.frame_ids[k]}
                photo_calib = photo_calibs.get(_photometric_key(overrides, config.photometric))
                overrides = {o: x for o, x in overrides.items() if not o.startswith("photometric_")}
                rc, why = _render_config(overrides, use_refined=variant != "raw", thesis_loop=not name.startswith("default"))
                if rc is None:
                    skipped[name] = why
                    warnings.warn(f"eval-views: method {name} skipped: {why}", stacklevel=2)
                    continue
                sub = cap if depth_sets.get(variant) is None else dataclasses.replace(cap, depth_refined=depth_sets[variant])
                if variant == "refined":
                    sub = dataclasses.replace(sub, depth_completed=completed)
                # Only methods that ask for it see a photometric calibration (the scene's own
                # photometric.json, if any, is not used: every method is defined by its overrides).
                sub = dataclasses.replace(sub, photometric=photo_calib if overrides.get("use_photometric") else None,
                                          render_filter_sigma_px=fitted if uses_fitted_filter(name) else None)
                loo = sub.subset(others)
                r = Renderer(loo, rc)
                if config.warmup:
                    r.render(f.T_world_cam, f.K)
                t1 = time.perf_counter()
                out = r.render(f.T_world_cam, f.K)
                ms = (time.perf_counter() - t1) * 1e3
                unfilled = None
            met = image_metrics(out, f.color, f.depth_m, unfilled,
                                completed=None if variant == "tsdf" else r.last.completed)
            met["ms_per_frame"] = ms
            per[name].append(met)
            if images_dir is not None:
                tid = cap.frame_ids[k]
                caption = (f"{tid} {name}: PSNR {met['psnr_db']:.2f} dB, covered {met['psnr_covered_db']:.2f}, "
                           f"holes {met['psnr_hole_db']:.2f}, SSIM {met['ssim']:.3f}, holes {100 * met['hole_frac']:.2f} %")
                write_png(Path(images_dir) / strip_name(tid, name),
                          eval_strip(f.color, out.color, out.valid, caption, panel_width=strip_width))
        if log is not None:
            log(f"target {cap.frame_ids[k]}: " + ", ".join(
                f"{n} {per[n][-1]['psnr_db']:.2f}" for n in config.methods if n not in skipped and per[n]))
    methods = {}
    for name in config.methods:
        if name in skipped or not per[name]:
            continue
        methods[name] = {m: float(np.nanmean([p[m] for p in per[name]])) if any(np.isfinite(p[m]) for p in per[name])
                         else float("nan") for m in METRICS}
    result = EvalResult(methods, {n: v for n, v in per.items() if v}, [cap.frame_ids[k] for k in targets],
                        skipped, refine_s)
    if images_dir is not None and result.per_target:
        write_report(Path(images_dir) / "report.md", format_table(result), result.target_ids, result.per_target,
                     protocol=f"Scene `{scene.meta.source}`: {len(result.target_ids)} targets; capture stride "
                              f"{config.stride}, a target every {config.target_every} capture frames.")
    return result


def format_table(result: EvalResult) -> str:
    """Markdown table of the per-method means."""
    lines = ["| method | PSNR dB | PSNR black dB | PSNR covered dB | PSNR holes dB | SSIM | hole % "
             "| PSNR no-depth dB | no-depth % | depth AbsRel | ms/frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    na = lambda x: "n/a" if not np.isfinite(x) else f"{x:.2f}"  # noqa: E731
    for name, m in result.methods.items():
        lines.append(f"| {name} | {m['psnr_db']:.2f} | {m['psnr_black_db']:.2f} | {m['psnr_covered_db']:.2f} | "
                     f"{na(m['psnr_hole_db'])} | {m['ssim']:.4f} | {100 * m['hole_frac']:.3f} | "
                     f"{na(m['psnr_nodepth_db'])} | {100 * m['nodepth_frac']:.3f} | {m['depth_absrel']:.4f} | "
                     f"{m['ms_per_frame']:.1f} |")
    for name, why in result.skipped.items():
        lines.append(f"| {name} | skipped: {why} | | | | | | | | | |")
    return "\n".join(lines)
