"""The pure per-frame pipeline of view synthesis (thesis §3.4.2-3.4.4).

    synthesize_frame(views, T_cam_world, K, config) -> FrameResult

``views`` (:class:`FrameViews`) is the frame's candidate list and what the loop asks of it; how its work is
scheduled is the executor's business (:mod:`presim.synthesis.execution`). Stages: view image (warp, crack
filter, composite) -> merge + hole analysis (adaptive loop) -> completion (holes take the warped views'
completed depth) -> resample -> blend -> fill -> smooth -> exposure. A backend is one table of the kernels of
the stages that have several (:class:`StageKernels`: :data:`NUMBA`, :data:`REFERENCE`, torch's from
:func:`stage_kernels`)."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Protocol

import numpy as np

from presim.geometry import Intrinsics, invert
from presim.imaging.gaussian import MIN_SIGMA_PX, smooth_colors, smooth_colors_ref
from presim.imaging.pushpull import pushpull_rgbd
from presim.photometric.apply import apply_exposure
from presim.synthesis import completion
from presim.synthesis import kernels_reference as ref
from presim.synthesis.blend import blend_numba, front_of_layers
from presim.synthesis.completion import CompletedPoints, Target
from presim.synthesis.config import RenderConfig
from presim.synthesis.cracks import (BANDED_MAX_LAYERS, TILED_MAX_FRAC, TILED_MIN_PIXELS, WARP_TILE_PX, crack_filter,
                                     filtered_composite_banded, warp_tiles)
from presim.synthesis.fill import fill_holes
from presim.synthesis.holes import HoleStats, analyse_hole_mask, merge_into_holes, merge_view_holes
from presim.synthesis.resample import SourceStack, resample_colors, resample_colors_ref
from presim.synthesis.warp import LayeredImage, ViewPoints, warp_layers

__all__ = ["STAGES", "ViewImage", "Workspace", "FrameViews", "FrameResult", "banded_applies", "StageKernels",
           "NUMBA", "REFERENCE", "stage_kernels", "synthesize_frame"]

STAGES = ("select", "load", "warp", "crack", "composite", "holes", "complete", "resample", "fill", "blend", "smooth",
          "exposure")
"""Keys of the per-stage milliseconds (``FrameResult.ms``, ``RenderStats.ms``)."""


@dataclass
class ViewImage:
    """One view warped, crack-filled and composited in the target camera."""

    depth_m: np.ndarray
    """float32 (H, W) z-depth, 0 = empty; exact at least on the ``replace`` pixels asked for."""
    color: np.ndarray
    warp_ms: float = 0.0
    crack_ms: float = 0.0
    composite_ms: float = 0.0
    load_ms: float = 0.0


@dataclass
class Workspace:
    """Buffers a backend reuses across views and frames (one per rendering thread)."""

    layers: LayeredImage | None = None
    front: tuple[np.ndarray, np.ndarray] | None = None
    """When set, ``(depth (H, W), color (H, W, 3))`` that the next view image also fills with the front-most
    surface of its warped layers (blending)."""


def banded_applies(config: RenderConfig, num_layers: int) -> bool:
    """Whether the numba backend runs the banded crack pass (3 x 3 switching median, few layers)."""
    return (config.crack_filter == "switching_median" and config.crack_kernel_px == 3
            and num_layers <= BANDED_MAX_LAYERS)


def view_image_numba(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, config: RenderConfig,
                     replace: np.ndarray | None, workspace: Workspace) -> ViewImage:
    """numba backend. With ``replace`` (bool (H, W), a later view) only those pixels are exact."""
    t0 = time.perf_counter()
    banded = banded_applies(config, view.num_layers)
    front = workspace.front
    # A later view's banded pass reads its layers only near the replaceable pixels (warp only the tiles
    # there), and colour only where depth > 0 (no clearing; the front surface for blending reads it all).
    tiles = None
    if banded and replace is not None and front is None and K.width * K.height >= TILED_MIN_PIXELS:
        tiles = warp_tiles(replace)
        if tiles.mean() > TILED_MAX_FRAC:  # holes everywhere: the full warp is cheaper
            tiles = None
    lay = workspace.layers = warp_layers(view, T_cam_world, K, config.near_m, workspace.layers, tiles=tiles,
                                         tile_px=WARP_TILE_PX, clear_color=not banded or front is not None)
    t1 = time.perf_counter()
    if front is not None:
        front_of_layers(lay.depth_m, lay.color, *front)
    if banded:
        d, c = filtered_composite_banded(lay.depth_m, lay.color, replace)
        return ViewImage(d, c, (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3)
    return _filtered_composite(lay.depth_m, lay.color, config, t0, t1)


def view_image_reference(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, config: RenderConfig,
                         replace: np.ndarray | None, workspace: Workspace) -> ViewImage:
    """Reference backend (plain numpy, :mod:`kernels_reference`); computes every pixel."""
    t0 = time.perf_counter()
    lay_d, lay_c = ref.warp_layers_ref(view.xyz_world, view.rgb, view.layer, view.num_layers,
                                       T_cam_world, K, config.near_m)
    if workspace.front is not None:
        front_of_layers(lay_d, lay_c, *workspace.front)
    return _filtered_composite(lay_d, lay_c, config, t0, time.perf_counter())


def _filtered_composite(lay_d: np.ndarray, lay_c: np.ndarray, config: RenderConfig, t0: float, t1: float
                        ) -> ViewImage:
    """Crack filter per layer, composite, crack filter of the seams: the reference (any mode and window)."""
    mode, kpx = config.crack_filter, config.crack_kernel_px
    d, c = crack_filter(lay_d, lay_c, mode, kpx)
    t2 = time.perf_counter()
    d, c = crack_filter(*ref.composite_layers_ref(d, c), mode, kpx)  # the seams
    return ViewImage(d, c, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (time.perf_counter() - t2) * 1e3)


class StageKernels(NamedTuple):
    """One backend's kernel of every stage that has several, with the numba functions' contracts (torch's bound to
    its device): the pipeline and the executor call only these."""

    view_image: Callable[..., ViewImage]
    """``(view, T_cam_world, K, config, replace, workspace)``: warp, crack filter, composite
    (:func:`view_image_numba`); the view in the backend's form (:class:`ViewPoints`, or a ``TorchView``)."""
    merge_view_holes: Callable[..., int]
    merge_into_holes: Callable[..., int]
    analyse_hole_mask: Callable[..., HoleStats]
    splat_into_holes: Callable[..., int]
    """The completion stage (:func:`presim.synthesis.completion.splat_into_holes`)."""
    resample: Callable[..., np.ndarray]
    """Backward colour sampling (:func:`presim.synthesis.resample.resample_colors`)."""
    pushpull: Callable[..., tuple]
    blend: Callable[..., np.ndarray]
    smooth: Callable[..., np.ndarray]
    """The reconstruction filter ``(color, sigma_px)``: a Gaussian of the output colour
    (:mod:`presim.imaging.gaussian`) that weighs the splats' placement (up to half a pixel off) and sensor noise
    against detail, sigma fitted per capture (docs/synthesis.md, item 13)."""
    apply_exposure: Callable[..., np.ndarray]
    upload: Callable[[ViewPoints], object] = lambda view: view
    """A prepared view in the backend's form (torch: a ``TorchView`` on its device)."""


NUMBA = StageKernels(view_image_numba, merge_view_holes, merge_into_holes, analyse_hole_mask,
                     completion.splat_into_holes, resample_colors, pushpull_rgbd, blend_numba, smooth_colors,
                     apply_exposure)
REFERENCE = NUMBA._replace(view_image=view_image_reference, splat_into_holes=completion.splat_into_holes_ref,
                           resample=resample_colors_ref, smooth=smooth_colors_ref)
"""The reference backend: numpy stages where they have a reference, numba's elsewhere."""


def stage_kernels(backend: str, device: str | None = None) -> StageKernels:
    """The kernels of ``backend`` (``"numba"``, ``"reference"`` or ``"torch"``: on ``device``, None = CUDA when
    present, else CPU; torch is imported only then)."""
    if backend != "torch":
        return REFERENCE if backend == "reference" else NUMBA
    from presim.imaging import torch_ops
    from presim.synthesis import torch_kernels as tk
    from presim.synthesis import torch_stages as ts

    def view_image_torch(view, T_cam_world: np.ndarray, K: Intrinsics, config: RenderConfig, replace, workspace
                         ) -> ViewImage:  # every pixel: no replace mask, no front surface (the blend re-warps)
        return ViewImage(*tk.view_image_torch(view, T_cam_world, K, config.near_m, config.crack_filter,
                                              config.crack_kernel_px))

    on = functools.partial
    merge = on(ts.merge_holes_torch, device=device)
    return StageKernels(view_image_torch, merge, merge, on(ts.analyse_hole_mask_torch, device=device),
                        on(tk.splat_into_holes_torch, device=device), on(tk.resample_colors_torch, device=device),
                        on(torch_ops.pushpull_rgbd_torch, device=device), on(ts.blend_torch, device=device),
                        on(torch_ops.smooth_colors_torch, device=device), on(ts.apply_exposure_torch, device=device),
                        on(tk.to_device, device=tk.resolve_device(device)))


class FrameViews(Protocol):
    """The views of one target camera, as the adaptive loop sees them."""

    candidates: list[int]
    """Ordered candidate view ids (scene frame indices), best first."""
    kernels: StageKernels
    """The backend of the stages after the view image that have several (:data:`NUMBA`, ...)."""
    smooth_sigma_px: float
    """Sigma of the reconstruction filter in this frame's pixels (0 = none)."""

    def view_image(self, view_id: int, replace: np.ndarray | None) -> ViewImage:
        """The view's image in the target camera (exact on ``replace``; everywhere when None)."""

    def ring(self) -> list[int]:
        """Further view ids (the ring beyond the candidates, nearest first) for the big holes the loop left."""

    def completed_points(self, warped: list[int]) -> list[CompletedPoints]:
        """The completed points of the views ``warped`` (empty when the scene has none)."""

    def next_view(self, pending: list[int], big_flat: np.ndarray, need_px: float | None, frac: float) -> int:
        """Index in ``pending`` of the first view whose grid puts >= 1 point and >= ``frac`` of the best count
        into the big holes ``big_flat`` (uint8 (H * W,)) and, with ``need_px``, is predicted to fill that many
        pixels; -1 when none can."""

    def blend(self, warped: list[int], color: np.ndarray, depth_m: np.ndarray, source: np.ndarray) -> np.ndarray:
        """The merged colour blended over the views that agree with its front surface."""

    def sources(self, warped: list[int]) -> SourceStack:
        """The source images of the views ``warped`` (backward colour sampling)."""

    def exposure(self, source: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The output exposure ``(A, b)`` of an image made of the views in ``source`` (None: keep it)."""


@dataclass(frozen=True)
class FrameResult:
    """One synthesized frame, and what the loop did."""

    color: np.ndarray
    """uint8 (H, W, 3), filled where no view covered when ``fill_holes``."""
    depth_m: np.ndarray
    """float32 (H, W)."""
    valid: np.ndarray
    """bool (H, W): synthesized from a view (not filled)."""
    source_view: np.ndarray
    """int32 (H, W): scene frame index of each pixel's view, -1 = none."""
    hole_frac: float
    """Fraction of pixels no view covered, before filling."""
    views: list[int]
    """Views warped, in order."""
    hole_frac_per_view: list[float]
    """Hole fraction after each merged view."""
    skipped: list[int]
    """Candidates left when the loop stopped because none can fill a big hole."""
    ms: dict[str, float]
    """Milliseconds per stage (keys: :data:`STAGES`)."""
    completed: np.ndarray | None = None
    """bool (H, W): pixels the completion stage covered (None when it did not run)."""


@dataclass
class _Loop:
    """The frame's image and what the adaptive loop did, while it draws views into it."""

    source: np.ndarray
    """int32 (H, W) view of each pixel (valid where ``holes`` is 0)."""
    ms: dict[str, float]
    t_start: float
    depth_m: np.ndarray | None = None
    color: np.ndarray | None = None
    holes: np.ndarray | None = None
    """uint8 (H, W), 1 = no view yet; None before the first view."""
    n_hole: int = 0
    replace: np.ndarray | None = None
    big: np.ndarray | None = None
    warped: list[int] = field(default_factory=list)
    hole_fracs: list[float] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)


def _ring_min_px(cfg: RenderConfig, K: Intrinsics) -> int:
    """Smallest hole (pixels) the ring writes."""
    return max(cfg.big_hole_px, int(np.ceil(cfg.ring_min_hole_frac * K.height * K.width)))


def _draw(views: FrameViews, kern: StageKernels, cfg: RenderConfig, K: Intrinsics, m: _Loop, pending: list[int],
          ring: bool = False) -> None:
    """The adaptive loop over ``pending`` (best first): merge each view's image into ``m`` on the replaceable
    pixels until no big hole is left or no candidate can fill one. The local group replaces the holes, big ones
    grown by ``hole_dilation_px``; the ``ring`` only the holes of at least ``ring_min_hole_frac`` of the image."""
    adaptive = cfg.fixed_views == 0
    big_px = _ring_min_px(cfg, K) if ring else cfg.big_hole_px  # the ring starts with m.replace = m.big
    dilation_px = 0 if ring else cfg.hole_dilation_px
    H, W = K.height, K.width
    n_target = len(m.warped) + (min(len(pending), cfg.ring_max_views) if ring else len(pending))
    stop_px = cfg.stop_hole_frac * H * W if adaptive else 0.0
    gain = max(cfg.min_view_gain, cfg.ring_min_hole_frac) if ring else cfg.min_view_gain
    need_px = gain * H * W if gain > 0 else None
    ms = m.ms
    while pending:
        if m.holes is not None and adaptive and cfg.time_budget_ms > 0 and \
                (time.perf_counter() - m.t_start) * 1e3 >= cfg.time_budget_ms:
            break  # time budget spent: deliver what we have (the fill closes the rest)
        best = 0
        if m.holes is not None and adaptive:
            t = time.perf_counter()
            best = views.next_view(pending, m.big.reshape(-1), need_px, cfg.next_view_fill_frac)
            ms["select"] += (time.perf_counter() - t) * 1e3
            if best < 0:  # no candidate can fill a big hole
                m.skipped.extend(pending)
                break
        vi = pending.pop(best)
        img = views.view_image(vi, m.replace)
        for stage in ("load", "warp", "crack", "composite"):
            ms[stage] += getattr(img, f"{stage}_ms")
        t = time.perf_counter()
        if m.holes is None:  # the first view's image is the accumulator
            m.depth_m, m.color = img.depth_m, img.color
            m.holes = np.empty((H, W), np.uint8)
            m.n_hole = kern.merge_view_holes(m.depth_m, m.color, m.source, None, m.depth_m, m.color, vi, m.holes)
        else:  # merge on the replaceable pixels, the hole mask updated in place
            m.n_hole -= kern.merge_into_holes(m.depth_m, m.color, m.source, m.replace, img.depth_m, img.color, vi,
                                              m.holes)
        m.warped.append(vi)
        last = len(m.warped) == n_target or not pending
        hs = kern.analyse_hole_mask(m.holes, m.n_hole, big_px, dilation_px, want_replace=not last,
                                    stop_px=stop_px, want_largest=not last)
        m.hole_fracs.append(hs.hole_frac)
        m.replace, m.big = (hs.big if ring else hs.replace), hs.big
        ms["holes"] += (time.perf_counter() - t) * 1e3
        if last or (adaptive and hs.largest_hole_px <= stop_px):
            break


def synthesize_frame(views: FrameViews, T_cam_world: np.ndarray, K: Intrinsics, config: RenderConfig
                     ) -> FrameResult:
    """The adaptive loop and the stages after it for one target camera (4x4 ``T_cam_world``, ``K``)."""
    cfg = config
    kern = views.kernels
    H, W = K.height, K.width
    ms = {s: 0.0 for s in STAGES}
    adaptive = cfg.fixed_views == 0
    m = _Loop(np.empty((H, W), np.int32), ms, time.perf_counter())
    warped = m.warped
    local = [int(v) for v in list(views.candidates)[:cfg.max_views if adaptive else cfg.fixed_views]]
    _draw(views, kern, cfg, K, m, local)
    completed = None
    if m.holes is not None and m.n_hole > 0 and cfg.use_completed_depth:
        t = time.perf_counter()
        points = views.completed_points(warped)
        if points:
            completed = m.holes != 0
            m.n_hole -= kern.splat_into_holes(points, T_cam_world, K, cfg.near_m,
                                              Target(m.depth_m, m.color, m.source, m.holes))
            completed &= m.holes == 0
        ms["complete"] = (time.perf_counter() - t) * 1e3
    ring_px = _ring_min_px(cfg, K)
    if adaptive and cfg.hole_candidates > 0 and completed is not None and m.n_hole >= ring_px:
        # holes neither the local group nor its completed depth covered: views further away, into those holes only
        # (without completed depth most holes are missing geometry, which a distant view sees through)
        t = time.perf_counter()
        hs = kern.analyse_hole_mask(m.holes, m.n_hole, ring_px, 0)
        ms["holes"] += (time.perf_counter() - t) * 1e3
        if hs.largest_hole_px >= ring_px:
            m.replace = m.big = hs.big
            _draw(views, kern, cfg, K, m, [v for v in views.ring() if v not in warped], ring=True)
    acc_d, acc_c, acc_src, n_hole = m.depth_m, m.color, m.source, m.n_hole
    if m.holes is None:  # no view warped: every pixel is a hole
        acc_d, acc_c, n_hole = np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.uint8), H * W
        acc_src.fill(-1)
    valid = acc_d > 0 if m.holes is None else m.holes == 0
    hole_frac = float(1.0 - (H * W - n_hole) / float(H * W))  # the same float operations as 1 - valid.mean()
    if cfg.backward_color and warped:
        t = time.perf_counter()
        acc_c = kern.resample(acc_c, acc_d, acc_src, K, invert(T_cam_world), views.sources(warped),
                              cfg.backward_depth_tol)
        ms["resample"] = (time.perf_counter() - t) * 1e3
    if cfg.blend and len(warped) > 1:
        t = time.perf_counter()
        acc_c = views.blend(warped, acc_c, acc_d, acc_src)
        ms["blend"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    if cfg.fill_holes and hole_frac > 0:
        # what the completion stage left is filled by pull-push under "auto" (RenderConfig.fill_method)
        method = "pushpull" if cfg.fill_method == "auto" and completed is not None else cfg.fill_method
        acc_c, acc_d = fill_holes(acc_c, acc_d, valid, method, background_rim_px=cfg.fill_background_px,
                                  pushpull=kern.pushpull)
    ms["fill"] = (time.perf_counter() - t) * 1e3
    if views.smooth_sigma_px >= MIN_SIGMA_PX:
        t = time.perf_counter()
        acc_c = kern.smooth(acc_c, views.smooth_sigma_px)
        ms["smooth"] = (time.perf_counter() - t) * 1e3
    if cfg.use_photometric and cfg.predict_exposure and cfg.exposure_frame is None and warped:
        t = time.perf_counter()
        exposure = views.exposure(acc_src)
        if exposure is not None:
            acc_c = kern.apply_exposure(acc_c, *exposure)
        ms["exposure"] = (time.perf_counter() - t) * 1e3
    return FrameResult(acc_c, acc_d, valid, acc_src, hole_frac, warped, m.hole_fracs, m.skipped, ms, completed)
