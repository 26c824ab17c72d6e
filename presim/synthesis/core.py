"""The pure per-frame synthesis core (thesis §3.4.2-3.4.4): one view's image, and the adaptive loop.

Two entry points, both free of renderer state (caches come in as arguments):

- a **view-image function** per backend, all with one signature (:data:`ViewImageFn`)::

      view_image(view, T_cam_world, K, config: ViewImageConfig, replace, workspace) -> ViewImage

  warps one prepared view's layers into the target camera, fills cracks per layer (switching
  median), composites the layers front to back and runs one crack pass over the layer seams. The
  backends (``numba``, ``reference``, ``torch``) are looked up in :data:`BACKEND_TABLE` through
  :func:`get_backend`; a backend is a :class:`SynthesisBackend` (its view-image function, how a
  :class:`~presim.synthesis.warp.ViewPoints` is moved to it, and how its device is chosen);
- :func:`synthesize_frame`: the adaptive loop over an ordered candidate list (from
  :func:`presim.synthesis.select.select_views`, made by the caller): pick the next view ->
  view image -> merge into the accumulated image -> hole analysis -> stop or add a view; then the
  final hole filling. Its knobs are :class:`FrameConfig` (built from ``RenderConfig`` by the
  Renderer).

Hooks for what other steps will add, all optional and inert by default:
``color_transform(view_idx, color) -> color`` is applied to each view image before it is merged
(per-view photometric correction); ``get_view(idx)`` is the caller's view provider (a level of
detail or a pose-corrected view can be returned there); the candidate list is an input, so
refinement or blending of the candidates happens outside the loop; a batched backend is one more
entry of :data:`BACKEND_TABLE`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from presim.capture.reprojection import nearest_pixel
from presim.geometry import Intrinsics, project, transform_points
from presim.synthesis import kernels_reference as ref
from presim.synthesis.composite import (PACKED_MAX_LAYERS, TILED_MAX_FRAC, TILED_MIN_PIXELS, WARP_TILE_PX,
                                        analyse_hole_mask, composite_layers, filtered_composite,
                                        filtered_composite_banded, filtered_composite_masked, filtered_composite_packed,
                                        merge_into_holes, merge_view_holes, warp_tiles)
from presim.synthesis.crack_filter import CRACK_FILTERS, crack_filter
from presim.synthesis.fill import FILL_KERNELS, FILL_METHODS, fill_holes
from presim.synthesis.grids import count_in_mask
from presim.synthesis.warp import LayeredImage, ViewPoints, warp_layers

__all__ = ["STAGES", "MASKED_MAX_FRAC", "BANDED_MIN_PIXELS", "ViewImageConfig", "ViewImage", "Workspace", "ViewImageFn",
           "SynthesisBackend", "BACKEND_TABLE", "BACKENDS", "get_backend", "view_image_numba",
           "view_image_reference", "FrameConfig", "FrameResult", "grid_pixels", "synthesize_frame"]

STAGES = ("select", "load", "warp", "crack", "composite", "holes", "fill", "blend")
"""Keys of the per-stage milliseconds (``FrameResult.ms``, ``RenderStats.ms``)."""

MASKED_MAX_FRAC = 0.12
"""numba: views after the first filter/composite only their replaceable pixels while these are
below this fraction of the image (measured crossover: ~350 ns per masked pixel vs ~19 ms CPU for
the dense per-layer filter + composite + seam pass at 640x480, L = 4)."""


BANDED_MIN_PIXELS = 0
"""numba, packed path: images of at least this many pixels run the crack pass fused in row bands
(:func:`presim.synthesis.composite.filtered_composite_banded`, one parallel region per view),
smaller ones the three-kernel chain (three regions; same output). 0: every size runs the bands.
Measured (docs/synthesis.md, "Small frames"): at 128x128 and 128x96 the band kernel took ~0.8x
the CPU of the chain per view with 2 threads (each parallel region costs ~50-100 us of CPU on the
shared 2-core machine); one thread alone (no region cost) had favoured the chain below ~200,000
pixels on the sample scene (0.80-0.86)."""


@dataclass(frozen=True)
class ViewImageConfig:
    """Knobs of one view's image (same meaning as the ``RenderConfig`` fields of the same names)."""

    near_m: float = 0.01
    """Points closer than this to the target camera are dropped."""
    crack_filter: str = "switching_median"
    """``"switching_median"`` (eq. 3.9), ``"median"`` (plain) or ``"none"``."""
    crack_kernel_px: int = 3
    """N of the N x N (switching) median window."""
    masked_max_frac: float = MASKED_MAX_FRAC
    """numba backend: masked filter/composite while the replaceable pixels are below this fraction
    (the column-count kernels, i.e. when ``packed_cracks`` is off or does not apply)."""
    packed_cracks: bool = True
    """numba backend, 3 x 3 switching median, <= 8 layers: crack mask first (packed per-layer
    occupancy counts; a window is read only where a median is taken), same output as the
    column-count kernels."""
    masked_warp: bool = True
    """numba backend, banded crack pass: a later view (with replaceable pixels) is warped, cleared
    and crack-filtered only in the tiles near its replaceable pixels (same output on them)."""

    def __post_init__(self) -> None:
        if self.crack_filter not in CRACK_FILTERS:
            raise ValueError(f"ViewImageConfig: crack_filter must be one of {CRACK_FILTERS}")
        if self.crack_kernel_px < 1 or self.crack_kernel_px % 2 == 0:
            raise ValueError("ViewImageConfig: crack_kernel_px must be odd")


@dataclass(frozen=True)
class ViewImage:
    """One view warped, crack-filled and composited in the target camera."""

    depth_m: np.ndarray
    """float32 (H, W) z-depth, 0 = empty. Exact at least on the ``replace`` pixels it was asked for
    (other pixels may be undefined when ``replace`` was given)."""
    color: np.ndarray
    """uint8 (H, W, 3)."""
    warp_ms: float = 0.0
    crack_ms: float = 0.0
    composite_ms: float = 0.0


@dataclass
class Workspace:
    """Buffers a backend may reuse across views and frames (the caller keeps one per renderer)."""

    layers: LayeredImage | None = None
    """numba: the (L, H, W) warp buffers."""
    ahead: Callable[[Any], Any] | None = None
    """numba: when set, ``ahead(view)`` -> the view warped fully for this target camera by a helper
    thread (:class:`presim.synthesis.warp_ahead.AheadImage`: its layers, and when the thread ran
    the banded crack pass too, the view's image), or None: then the view is warped here. Used only
    where the view would be warped fully (no tiles)."""
    front: tuple[np.ndarray, np.ndarray] | None = None
    """numba: when set, ``(depth (H, W), color (H, W, 3))`` that the next view image also fills with
    the front-most surface of its warped layers (smallest depth, no crack filter; multi-view
    blending keeps it, :func:`presim.synthesis.blend.front_of_layers`)."""


class ViewImageFn(Protocol):
    def __call__(self, view: Any, T_cam_world: np.ndarray, K: Intrinsics, config: ViewImageConfig,
                 replace: np.ndarray | None, workspace: Workspace) -> ViewImage: ...


def view_image_numba(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, config: ViewImageConfig,
                     replace: np.ndarray | None, workspace: Workspace) -> ViewImage:
    """numba backend: warp (reusing ``workspace`` buffers) + fused filter/composite + seam pass.

    With ``replace`` (bool (H, W)) covering less than ``config.masked_max_frac`` of the image and the
    switching median, only the replaceable pixels are computed (the rest is undefined).
    """
    t0 = time.perf_counter()
    mode, kpx = config.crack_filter, config.crack_kernel_px
    packed = (config.packed_cracks and mode == "switching_median" and kpx == 3
              and view.num_layers <= PACKED_MAX_LAYERS)
    banded = packed and workspace.front is None and K.width * K.height >= BANDED_MIN_PIXELS
    # A later view's banded crack pass reads its layers only near the replaceable pixels: warp
    # (and clear) only the tiles there (same output on those pixels).
    tiles = None
    if banded and replace is not None and config.masked_warp and K.width * K.height >= TILED_MIN_PIXELS:
        tiles = warp_tiles(replace)
        if tiles.mean() > TILED_MAX_FRAC:  # holes everywhere: the full warp is cheaper
            tiles = None
    got = workspace.ahead(view) if tiles is None and workspace.ahead is not None else None
    if got is not None and got.depth_m is not None:  # warped and crack-filtered ahead
        if banded:
            d, c = got.depth_m, got.color
            if replace is None:  # the first view's image becomes the frame's: not the thread's buffers
                d, c = d.copy(), c.copy()
            return ViewImage(d, c, (time.perf_counter() - t0) * 1e3, 0.0, 0.0)
        got = None  # its layers' colour planes were not cleared (only the banded pass reads them so)
    if got is not None:
        lay = got.layers
    else:
        # the banded crack pass reads the layers' colour only where their depth is > 0: the colour
        # planes need no clearing for it (3 of the 7 bytes per layer pixel)
        lay = workspace.layers = warp_layers(view, T_cam_world, K, config.near_m, workspace.layers, tiles=tiles,
                                             tile_px=WARP_TILE_PX, clear_color=not banded)
    t1 = time.perf_counter()
    if packed:
        # Filter + composite + seam pass in one call; later views only on their replaceable pixels.
        if banded:  # one pass over bands of rows, or runs of tiles with replaceable pixels (same output)
            d, c = filtered_composite_banded(lay.depth_m, lay.color, replace)
        else:
            d, c = filtered_composite_packed(lay.depth_m, lay.color, replace, workspace.front)
        return ViewImage(d, c, (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3, 0.0)
    if workspace.front is not None:  # the other kernels keep no occupancy pass to share
        from presim.synthesis.blend import front_of_layers

        front_of_layers(lay.depth_m, lay.color, *workspace.front)
    if replace is not None and mode == "switching_median" and replace.mean() < config.masked_max_frac:
        # Later views only write into the replaceable region: filter/composite just there.
        d, c = filtered_composite_masked(lay.depth_m, lay.color, replace, kpx, seam_pass=True)
        return ViewImage(d, c, (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3, 0.0)
    if mode == "switching_median":  # per-layer filter fused with the composite
        d, c = filtered_composite(lay.depth_m, lay.color, kpx)
        t2 = time.perf_counter()
    else:
        d, c = crack_filter(lay.depth_m, lay.color, mode, kpx)
        t2 = time.perf_counter()
        d, c = composite_layers(d, c)
    # Second pass on the composite: cracks along layer seams and at crossings of crack lines
    # (4 of 9 neighbours before the first pass filled the lines).
    d, c = crack_filter(d, c, mode, kpx)
    t3 = time.perf_counter()
    return ViewImage(d, c, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3)


def view_image_reference(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, config: ViewImageConfig,
                         replace: np.ndarray | None, workspace: Workspace) -> ViewImage:
    """Reference backend (plain numpy/Python, :mod:`kernels_reference`); computes every pixel."""
    t0 = time.perf_counter()
    lay_d, lay_c = ref.warp_layers_ref(view.xyz_world, view.rgb, view.layer, view.num_layers,
                                       T_cam_world, K, config.near_m)
    t1 = time.perf_counter()
    kpx = config.crack_kernel_px
    filt = {"switching_median": ref.switching_median_ref, "median": ref.plain_median_ref}.get(config.crack_filter)
    if filt is not None:
        pairs = [filt(lay_d[i], lay_c[i], kpx) for i in range(view.num_layers)]
        lay_d = np.stack([p[0] for p in pairs])
        lay_c = np.stack([p[1] for p in pairs])
    t2 = time.perf_counter()
    d, c = ref.composite_layers_ref(lay_d, lay_c)
    if filt is not None:
        d, c = filt(d, c, kpx)
    return ViewImage(d, c, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (time.perf_counter() - t2) * 1e3)


@dataclass(frozen=True)
class SynthesisBackend:
    """What the Renderer needs from a backend."""

    name: str
    view_image: ViewImageFn
    """The backend's view-image function (:data:`ViewImageFn`)."""
    upload: Callable[[ViewPoints, Any], Any]
    """``upload(view_points, device)`` -> the view in the form ``view_image`` takes (cached)."""
    resolve_device: Callable[[str | None], Any]
    """``resolve_device(name_or_None)`` -> the device object passed to ``upload``."""
    frame_batch: Callable[..., Any] | None = None
    """Optional: renders many frames in one call (``Renderer.render_batch`` uses it), e.g.
    :func:`presim.synthesis.batch_torch.synthesize_batch_torch`."""


def _host_view(view: ViewPoints, device: Any) -> ViewPoints:
    return view


def _no_device(name: str | None) -> None:
    return None


def _numba_backend() -> SynthesisBackend:
    return SynthesisBackend("numba", view_image_numba, _host_view, _no_device)


def _reference_backend() -> SynthesisBackend:
    return SynthesisBackend("reference", view_image_reference, _host_view, _no_device)


def _torch_backend() -> SynthesisBackend:
    from presim.synthesis import torch_backend as tb  # torch is imported only when asked for

    return SynthesisBackend("torch", tb.view_image_torch, tb.to_device, tb.resolve_device)


def _torch_batch_backend() -> SynthesisBackend:
    from presim.synthesis import batch_torch as bt  # torch is imported only when asked for
    from presim.synthesis import torch_backend as tb

    return SynthesisBackend("torch_batch", tb.view_image_torch, tb.to_device, tb.resolve_device,
                            bt.synthesize_batch_torch)


BACKEND_TABLE: dict[str, Callable[[], SynthesisBackend]] = {
    "numba": _numba_backend,
    "reference": _reference_backend,
    "torch": _torch_backend,
    "torch_batch": _torch_batch_backend,
}
"""Backend name -> factory of its :class:`SynthesisBackend` (factories keep torch imports lazy)."""

BACKENDS = tuple(BACKEND_TABLE)


def get_backend(name: str) -> SynthesisBackend:
    """The :class:`SynthesisBackend` called ``name`` (one of :data:`BACKENDS`)."""
    if name not in BACKEND_TABLE:
        raise ValueError(f"backend must be one of {BACKENDS}, got {name!r}")
    return BACKEND_TABLE[name]()


# ---- the adaptive loop -----------------------------------------------------------------------

@dataclass(frozen=True)
class FrameConfig:
    """Knobs of :func:`synthesize_frame` (same meaning as the ``RenderConfig`` fields of the same
    names; ``RenderConfig.frame_config()`` builds it)."""

    view: ViewImageConfig = field(default_factory=ViewImageConfig)
    """Per-view image knobs."""
    fixed_views: int = 0
    """> 0: warp exactly the first this many candidates (no adaptive loop)."""
    max_views: int = 6
    """The adaptive loop draws from the first ``max_views`` candidates only."""
    stop_hole_frac: float = 0.0005
    """The adaptive loop stops when the largest connected hole is at most this fraction."""
    big_hole_px: int = 16
    """Holes of at least this many pixels are big (dilated; the next view must land in them)."""
    hole_dilation_px: int = 2
    """Dilation radius of big holes (ghost contours)."""
    next_view_fill_frac: float = 0.0
    """Next view = first candidate whose grid puts >= 1 and >= this fraction of the best count of
    points into the big holes."""
    fill_holes: bool = True
    """Fill the pixels no view covers (they stay invalid)."""
    fill_method: str = "auto"
    """``"auto"``, ``"telea"`` or ``"pushpull"``."""
    fill_kernel: str = "numba"
    """Fill implementation (pull-push and Telea): ``"numba"`` or ``"opencv"``
    (:data:`presim.synthesis.fill.FILL_KERNELS`)."""
    time_budget_ms: float = 0.0
    """> 0: the adaptive loop adds no view once the frame has run this long (0 = no budget)."""
    min_view_gain: float = 0.0
    """> 0: the adaptive loop adds a view only when its grid predicts that it fills at least this
    fraction of the image (the target pixels its grid points in big holes stand for,
    ``grid_fill``); 0 = any view that fills at least one grid point."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_view_gain < 1.0:
            raise ValueError("FrameConfig: min_view_gain must be in [0, 1)")
        if self.fixed_views < 0 or self.max_views < 1:
            raise ValueError("FrameConfig: fixed_views must be >= 0 and max_views >= 1")
        if self.fill_method not in FILL_METHODS:
            raise ValueError(f"FrameConfig: fill_method must be one of {FILL_METHODS}")
        if self.fill_kernel not in FILL_KERNELS:
            raise ValueError(f"FrameConfig: fill_kernel must be one of {FILL_KERNELS}")


@dataclass(frozen=True)
class FrameResult:
    """One synthesized frame, and what the loop did."""

    color: np.ndarray
    """uint8 (H, W, 3) (filled where no view covered when ``fill_holes``)."""
    depth_m: np.ndarray
    """float32 (H, W)."""
    valid: np.ndarray
    """bool (H, W): synthesized from a view (not filled)."""
    source_view: np.ndarray
    """int32 (H, W): candidate id (scene frame index) of each pixel's view, -1 = none."""
    hole_frac: float
    """Fraction of pixels no view covered, before filling."""
    views: list[int]
    """Candidates warped, in order."""
    hole_frac_per_view: list[float]
    """Hole fraction after each merged view."""
    skipped: list[int]
    """Candidates left when the loop stopped because none can fill a big hole."""
    ms: dict[str, float]
    """Milliseconds per stage (keys: :data:`STAGES`; "select" = the hole-fill tests here)."""


def grid_pixels(grid_xyz_world: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics, near_m: float) -> np.ndarray:
    """Flat pixel indices (v * W + u) where a view's sub-sampled grid (m, 3) lands in the target."""
    if len(grid_xyz_world) == 0:
        return np.zeros(0, np.int64)
    uv, z = project(K, transform_points(T_cam_world, grid_xyz_world))
    ok = z > near_m
    u, v, inb = nearest_pixel(uv[ok], K.width, K.height)
    return v[inb] * K.width + u[inb]


def synthesize_frame(candidates: Sequence[int], T_cam_world: np.ndarray, K: Intrinsics, config: FrameConfig,
                     view_image: ViewImageFn, get_view: Callable[[int], Any],
                     get_grid: Callable[[int], np.ndarray], workspace: Workspace | None = None,
                     color_transform: Callable[[int, np.ndarray], np.ndarray] | None = None,
                     blend: Callable[[list[int], np.ndarray, np.ndarray, np.ndarray],
                                     tuple[np.ndarray, float]] | None = None,
                     grid_px: Callable[[int], np.ndarray] | None = None,
                     grid_fill: Callable[[int, np.ndarray], float] | None = None,
                     hole_scores: Callable[[list[int], np.ndarray], tuple[list[int], list[float]]] | None = None,
                     next_view: Callable[[list[int], np.ndarray, float | None, float], int] | None = None
                     ) -> FrameResult:
    """The adaptive loop (thesis §3.4.2-3.4.4) and the final fill for one target camera.

    Args:
        candidates: ordered candidate view ids (scene frame indices), best first.
        T_cam_world: 4x4 world -> target camera; K: target intrinsics.
        config: :class:`FrameConfig`.
        view_image: a backend's :data:`ViewImageFn`.
        get_view: ``get_view(id)`` -> the prepared view in the backend's form (the caller caches).
        get_grid: ``get_grid(id)`` -> (m, 3) world points of the view's sub-sampled grid (used to
            test whether a candidate can fill a big hole).
        workspace: buffers the backend may reuse (a fresh one when None).
        color_transform: optional ``(id, color (H, W, 3) uint8) -> color`` applied to each view's
            image before it is merged (None: colors as warped).
        blend: optional ``(views, color, depth, source) -> (color, ms)`` run on the merged image
            before the final fill (multi-view blending, :mod:`presim.synthesis.blend`); None = the
            winner's colours.
        grid_px: optional fast path: ``grid_px(id)`` -> the flat target pixels of the view's grid
            (= :func:`grid_pixels` of ``get_grid(id)``; the Renderer projects all candidates' grids
            once per frame, :class:`presim.synthesis.grids.FrameGrids`).
        grid_fill: optional ``grid_fill(id, big_flat)`` -> the target pixels that the view's grid points
            landing on ``big_flat`` (uint8/bool (H * W,), the big holes) stand for (the Renderer: each
            point's ``(overlap stride x z_src / z_target x f_target / f_src)^2``,
            :meth:`presim.synthesis.grids.FrameGrids.fill_area`); with ``config.min_view_gain`` > 0
            a candidate is warped only when it reaches ``min_view_gain x H x W`` (None: that rule is off).
        hole_scores: optional fast path of both tests for all pending candidates at once:
            ``hole_scores(ids, big_flat)`` -> ``(counts, fills)`` with ``counts[k]`` = the number of
            ``grid_px(ids[k])`` on ``big_flat`` and ``fills[k]`` = ``grid_fill(ids[k], big_flat)``
            (:meth:`presim.synthesis.grids.FrameGrids.hole_scores`, one kernel call; the reference
            of ``next_view``, which the Renderer passes).
        next_view: optional fast path of the whole choice: ``next_view(ids, big_flat, need, frac)`` ->
            the index in ``ids`` of the next view by the rules below from ``hole_scores``' counts and
            fills (``need``: the fill a view must reach, None when ``min_view_gain`` is 0; ``frac``:
            ``next_view_fill_frac``), or -1 when none can fill a big hole (the Renderer:
            :meth:`presim.synthesis.grids.FrameGrids.next_view`, one kernel call, no per-view lists).
    Returns:
        :class:`FrameResult`.
    """
    cfg = config
    H, W = K.height, K.width
    ws = workspace if workspace is not None else Workspace()
    ms = {s: 0.0 for s in STAGES}
    adaptive = cfg.fixed_views == 0
    # The adaptive loop considers the first max_views candidates (bounds the frame time).
    pending = [int(v) for v in list(candidates)[:cfg.max_views if adaptive else cfg.fixed_views]]
    n_target = len(pending)
    # The first view's image becomes the accumulator and its merge writes every source id; a frame
    # without any view gets empty buffers after the loop.
    acc_d = acc_c = None
    acc_src = np.empty((H, W), np.int32)
    holes = None  # uint8 (H, W) hole mask of the accumulated image, 1 = empty (after the first view)
    views: list[int] = []
    hole_fracs: list[float] = []
    skipped: list[int] = []
    stop_px = cfg.stop_hole_frac * H * W
    replace = big = None
    if grid_px is None:
        def grid_px(v: int) -> np.ndarray:
            return grid_pixels(get_grid(v), T_cam_world, K, cfg.view.near_m)
    px_of: dict[int, np.ndarray] = {}
    t_start = time.perf_counter()
    while pending and len(views) < n_target:
        if views and adaptive and cfg.time_budget_ms > 0 and (time.perf_counter() - t_start) * 1e3 >= cfg.time_budget_ms:
            break  # time budget spent: deliver what we have (the fill closes the rest)
        if views and adaptive:
            # Next view by how many of its sampled grid points land in the big holes; none lands
            # there -> no candidate can help, stop.
            t = time.perf_counter()
            big_flat = big.reshape(-1)
            gain = cfg.min_view_gain > 0 and (grid_fill is not None or hole_scores is not None)
            need = cfg.min_view_gain * H * W
            if next_view is not None:
                best = next_view(pending, big_flat, need if cfg.min_view_gain > 0 else None, cfg.next_view_fill_frac)
                ms["select"] += (time.perf_counter() - t) * 1e3
                if best < 0:
                    skipped.extend(pending)
                    break
                counts = None
            elif hole_scores is not None:
                counts, fills = hole_scores(pending, big_flat)
                if gain:
                    counts = [n if n > 0 and f >= need else 0 for n, f in zip(counts, fills)]
            else:
                for v in pending:  # each candidate's grid is projected once per frame
                    if v not in px_of:
                        px_of[v] = grid_px(v)
                counts = [int(count_in_mask(big_flat, px_of[v])) for v in pending]
                if gain:
                    # Diminishing returns: a candidate must be predicted to fill enough of the image.
                    counts = [n if n > 0 and grid_fill(v, big_flat) >= need else 0 for n, v in zip(counts, pending)]
            if counts is not None:
                ms["select"] += (time.perf_counter() - t) * 1e3
                cmax = max(counts)
                if cmax == 0:
                    skipped.extend(pending)
                    break
                best = next(i for i, n in enumerate(counts) if n > 0 and n >= cfg.next_view_fill_frac * cmax)
            vi = pending.pop(best)
        else:
            vi = pending.pop(0)
        t = time.perf_counter()
        view = get_view(vi)
        ms["load"] += (time.perf_counter() - t) * 1e3
        img = view_image(view, T_cam_world, K, cfg.view, replace, ws)
        ms["warp"] += img.warp_ms
        ms["crack"] += img.crack_ms
        ms["composite"] += img.composite_ms
        d, c = img.depth_m, img.color
        if color_transform is not None:
            c = color_transform(vi, c)
        t = time.perf_counter()
        if replace is None:
            # the first view's image is the accumulator: its source ids + hole mask + hole count, one pass
            acc_d, acc_c = d, c
            holes = np.empty((H, W), np.uint8)
            n_hole = merge_view_holes(acc_d, acc_c, acc_src, None, d, c, vi, holes)
        else:  # merge on the replaceable pixels, the hole mask updated in place
            n_hole -= merge_into_holes(acc_d, acc_c, acc_src, replace, d, c, vi, holes)
        views.append(vi)
        last = len(views) == n_target or not pending
        hs = analyse_hole_mask(holes, n_hole, cfg.big_hole_px, cfg.hole_dilation_px, want_replace=not last,
                               stop_px=stop_px if adaptive else 0.0, want_largest=not last)
        hole_fracs.append(hs.hole_frac)
        replace, big = hs.replace, hs.big
        ms["holes"] += (time.perf_counter() - t) * 1e3
        if last or (adaptive and hs.largest_hole_px <= stop_px):
            break
    if holes is None:  # no view warped
        acc_d = np.zeros((H, W), np.float32)
        acc_c = np.zeros((H, W, 3), np.uint8)
        acc_src.fill(-1)
        valid = acc_d > 0
        hole_frac = float(1.0 - valid.mean())
    else:  # the last merge's hole mask; the same float operations as 1 - valid.mean()
        valid = holes == 0
        hole_frac = float(1.0 - (H * W - n_hole) / float(H * W))
    if blend is not None and len(views) > 1:  # ---- blend hook (presim/synthesis/blend.py) ----
        acc_c, ms["blend"] = blend(views, acc_c, acc_d, acc_src)
    t = time.perf_counter()
    if cfg.fill_holes and hole_frac > 0:
        acc_c, acc_d = fill_holes(acc_c, acc_d, valid, cfg.fill_method, kernel=cfg.fill_kernel)
    ms["fill"] = (time.perf_counter() - t) * 1e3
    return FrameResult(acc_c, acc_d, valid, acc_src, hole_frac, views, hole_fracs, skipped, ms)
