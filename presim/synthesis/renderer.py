"""Renderer: the thin stateful component of the view synthesis engine (thesis §3.4.2-3.4.4).

    Renderer(scene, RenderConfig()).render(T_world_cam, K) -> RGBD
    Renderer(...).render_batch(T_world_cams (B, 4, 4), K) -> list[RGBD]

Per frame: select views (:mod:`select`), then the pure per-frame core (:mod:`core`,
:func:`~presim.synthesis.core.synthesize_frame` with this renderer's caches and its backend's
view-image function from :data:`~presim.synthesis.core.BACKEND_TABLE`): for each selected view in
order — warp it in L layers
with a z-buffer per layer (:mod:`warp`), fill cracks in every layer with the switching median
(:mod:`crack_filter`), composite the layers front to back plus one crack pass over the layer seams,
and merge it into the target image on the pixels still missing (holes, big ones dilated against
ghost contours; :mod:`composite`). The adaptive loop stops once the largest hole is below
``stop_hole_frac`` of the image. Pixels no view covers are filled last (:mod:`fill`) and stay
``valid=False``.

State kept per scene (built once, never per frame):
- camera centres, optical axes and FOVs of all views (for selection), at construction;
- per view, lazily: world points sorted by layer + colors (:class:`warp.ViewPoints`, ~15 bytes per
  valid pixel, 4.6 MB for a full 640x480 view) in an LRU cache bounded by ``cache_mb``; the small
  sub-sampled overlap grids (~1200 points per view) in an unbounded dict.
Frames are read from the scene's FrameSource only when a view is first needed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import mmap
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numba
import numpy as np

from presim.capture.scene import Scene, SceneError
from presim.geometry import Intrinsics, check_rigid, invert, transform_points, unproject_depth
from presim.synthesis.blend import BlendConfig, blend_frame, blend_stacks, front_image_points
from presim.synthesis.core import (BACKENDS, STAGES, FrameConfig, ViewImageConfig, Workspace, get_backend,
                                   synthesize_frame)
from presim.synthesis.composite import PACKED_MAX_LAYERS, TILED_MIN_PIXELS
from presim.synthesis.crack_filter import CRACK_FILTERS
from presim.synthesis.fill import FILL_KERNELS, FILL_METHODS
from presim.synthesis.grids import FrameGrids
from presim.synthesis.lod import LodConfig, build_level, choose_level, footprint_ratio
from presim.synthesis.photometric import OutputVignetting, SourceColorCorrection
from presim.synthesis.rgbd import RGBD
from presim.synthesis.sharpness import ViewSharpness
from presim.synthesis.threads import FrameModeChooser, frame_threads, numba_threads, serial_kernels, serial_now
from presim.synthesis.select import SELECTION_MODES, VIEW_ORDERS, Selection, select_views
from presim.synthesis.view_cache import ViewCache
from presim.synthesis.warp import LayeredImage, ViewPoints, prepare_view
from presim.synthesis.warp_ahead import WARP_AHEAD_MIN_POINTS, WarpAhead

__all__ = ["BACKENDS", "STAGES", "RenderConfig", "RenderStats", "Renderer"]


def _unmap_pages(arr: np.ndarray) -> None:
    """Drop this process's mapping of the pages of ``arr`` when it is a slice of a read-only memory map
    (a saved scene's colour/depth arrays): the prepared view holds copies, so the pages would only sit
    in the process's RSS (they stay in the page cache; a later read maps them again). No-op otherwise."""
    mm, b = None, arr
    while b is not None and mm is None:  # np.asarray(memmap[i]) is a plain view: find the map below
        mm, b = getattr(b, "_mmap", None), getattr(b, "base", None)
    if mm is None or arr.flags.writeable or not hasattr(mmap, "MADV_DONTNEED") or arr.nbytes == 0:
        return
    try:
        start = arr.ctypes.data - np.frombuffer(mm, np.uint8).ctypes.data
        lo = start // mmap.PAGESIZE * mmap.PAGESIZE
        hi = min(len(mm), -(-(start + arr.nbytes) // mmap.PAGESIZE) * mmap.PAGESIZE)
        if 0 <= lo < hi:
            mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
    except (ValueError, OSError, TypeError):  # closed map, unusual layout: keep the pages
        pass


@dataclass(frozen=True)
class RenderConfig:
    """Knobs of the synthesis pipeline. Defaults are the full thesis pipeline."""

    num_layers: int = 4
    """L of layered warping (thesis: 4 is the quality/speed trade-off); 1 = plain DIBR z-buffer."""
    selection: str = "adaptive"
    """``"adaptive"`` (thesis: distance -> angle vs FOV -> overlap), ``"distance"`` (nearest centres
    only) or ``"angle"`` (smallest viewing-direction angle only)."""
    fixed_views: int = 0
    """> 0: warp exactly this many selected views (no adaptive loop), e.g. 1, 2, 3 as Table 3.5."""
    max_candidates: int = 10
    """Size of the local group (top-k by camera-centre distance, eq. 3.5)."""
    crack_filter: str = "switching_median"
    """``"switching_median"`` (eq. 3.9), ``"median"`` (plain) or ``"none"``."""
    hole_dilation_px: int = 2
    """Big holes are dilated by this radius before the next view fills them (ghost contours)."""
    use_refined_depth: bool = True
    """Use ``scene.depth_refined`` (``presim refine``) when present, else the raw depth."""
    use_fused_depth: bool = False
    """Use ``scene.depth_fused`` (``presim fuse``: sensor depth aligned to and fused with the refined
    depth, thesis §5.3.4) when present; it takes precedence over ``use_refined_depth``."""
    fill_holes: bool = True
    """Fill pixels no view covers (they stay False in ``RGBD.valid``); False leaves them 0."""
    backend: str = "numba"
    """``"numba"`` (fast CPU), ``"reference"`` (slow numpy, for tests) or ``"torch"`` (CUDA if
    present, else CPU)."""
    max_views: int = 6
    """The adaptive loop draws from the first ``max_views`` selected views only (a pose outside the
    capture has holes no view can fill; this bounds the frame time)."""
    stop_hole_frac: float = 0.0005
    """The adaptive loop stops when the largest connected hole is at most this fraction of the
    image (0.05 %: 154 px at 640x480)."""
    big_hole_px: int = 16
    """Holes of at least this many pixels count as big and are dilated by ``hole_dilation_px``."""
    crack_kernel_px: int = 3
    """N of the N x N (switching) median window."""
    packed_cracks: bool = True
    """numba backend, 3 x 3 switching median, <= 8 layers: find the cracks first from packed
    per-layer occupancy counts and read a window only where a median is taken (same output as
    False, the previous column-count kernels; 2-3x less CPU for the crack stage on the apc capture
    at 640x480, docs/synthesis.md)."""
    masked_warp: bool = True
    """numba backend, packed crack pass: a view after the first is warped, cleared and crack-filtered
    only in the 16 x 16 tiles within 2 pixels of its replaceable pixels, the only pixels it may
    write (same output as False, which warps and filters the whole image for every view). Applies
    from ``composite.TILED_MIN_PIXELS`` pixels on and while at most ``composite.TILED_MAX_FRAC`` of
    the tiles are active (docs/synthesis.md, "Later views on tiles")."""
    view_order: str = "distance"
    """Warp order of the selected views: ``"distance"`` (nearest first; measured better on the real
    capture) or ``"overlap"`` (largest first)."""
    overlap_stride_px: int = 8
    """Sampling interval of the grid projected for the overlap test and for the adaptive loop's
    "can this view fill a hole at all" test (8 px: a 154 px hole holds ~2 grid points)."""
    fill_method: str = "auto"
    """Final hole filling: ``"auto"``, ``"telea"`` or ``"pushpull"`` (see presim.synthesis.fill)."""
    fill_kernel: str = "numba"
    """Fill implementation. ``"numba"``: pull-push (colour above the Telea limit, depth always)
    reading uint8 colour and depth directly and writing only the holes at full size (~2x less CPU
    than ``"opencv"`` at 640x480 with 23 % holes, measured), and Telea inpainting in numba
    (:mod:`presim.synthesis.telea`, the same pixels as ``cv2.inpaint``, 1.5-3.5x faster). ``"opencv"``:
    the earlier resize-based pull-push (fills differ by < 1 grey level on average) and
    ``cv2.inpaint`` (docs/synthesis.md)."""
    cache_mb: float = 1024.0
    """Bound of the per-view point cache (LRU), MiB."""
    prefetch: bool = True
    """numba backend: when a frame starts, hand the selected candidates 2..``max_views`` that have
    no cached level yet to one background thread, which prepares them at the level of detail this
    frame picks for them while the frame renders, so that a camera moving through the scene finds
    them ready (:mod:`presim.synthesis.view_cache`). The images do not depend on it; it uses a
    second core where the frame leaves one idle."""
    near_m: float = 0.01
    """Points closer than this to the target camera are dropped."""
    next_view_fill_frac: float = 0.0
    """Adaptive loop: the next view is the first candidate (selection order) whose sampled grid puts
    at least one point and at least this fraction of the best candidate's count into the big holes.
    0 = selection order, skipping views that cannot fill anything (default); 1 = greedy max
    coverage. Among the max_views candidates both measured within 0.1 dB on the real capture and
    the synthetic room (drawing greedily from all 10 candidates cost 0.7 dB on the real capture:
    far views are less well aligned)."""
    max_zoom: float = 1.0
    """A target sampling the scene more densely than this factor x the capture (focal length ratio)
    is rendered at a lower internal resolution and upsampled: one-pixel splats cannot cover a
    surface magnified more than ~1.5x (cracks 2 px wide defeat any 3x3 median), and the capture
    has no finer detail to give. The output always has the requested size and intrinsics.
    Measured at 1280x720 against exact ray-cast images (benchmarks/bench_render_zoom.py): 1.0 is
    within 0.2 dB of 1.15 and 1.3 at 1/2 to 1/5 of their time."""
    torch_device: str | None = None
    """Torch device (``None``: CUDA when available, else CPU)."""
    lod_levels: int = 3
    """Level of detail (:mod:`presim.synthesis.lod`): coarsest pyramid level of a view's points
    (2x2 depth-aware pooling per level); 0 = always warp every point. A frame uses, per view, the
    coarsest level whose points still cover at most ``lod_max_footprint`` target pixels: a target
    sampled like the capture (e.g. 640x480 from 640x480 views) stays at level 0, unchanged."""
    lod_max_footprint: float = 1.0
    """Target pixels one point of the chosen level may cover (median over the view's grid)."""
    lod_depth_tol: float = 0.02
    """Relative depth band of the front surface pooled together in a 2x2 block."""
    reuse_move_m: float = 0.01
    """Temporal coherence: a frame whose camera moved at most this far (and turned at most
    ``reuse_turn_deg``) from the previous frame, with the same intrinsics, reuses the previous
    frame's view selection (candidate list); 0 disables."""
    reuse_turn_deg: float = 1.0
    """Rotation bound of the selection reuse, degrees."""
    min_view_gain: float = 0.005
    """Adaptive loop, diminishing returns: a further view is warped only when its sub-sampled grid
    predicts that it fills at least this fraction of the image (the target pixels its grid points
    in big holes stand for, each ``(overlap_stride_px x z_src / z_target x f_target / f_src)^2``); 0 = the
    thesis's loop (any view that can fill a big hole at all). 0.005 warps 3.6 instead of 6.0 views
    per frame on the apc capture at 640x480 with `eval-views` PSNR/SSIM within 0.04 dB / 0.0013
    of 0 (docs/synthesis.md, "Diminishing returns")."""
    time_budget_ms: float = 0.0
    """> 0: the adaptive loop adds no further view once the frame has taken this long (the view
    budget is ``max_views``); the final fill still runs. 0 = no time budget."""
    threads: int = 0
    """numba threads per frame: 0 = auto (one thread for frames of at most
    ``threads.SERIAL_MAX_PIXELS`` = 40 000 pixels, where waking a second thread for each parallel
    kernel costs more than it gives, else numba's current count); > 0 = that many. The images do not
    depend on it (docs/synthesis.md, "Threads per frame")."""
    warp_ahead: bool = True
    """numba backend, ``threads`` = 0, blending off, not inside :meth:`Renderer.render_batch`'s
    threads: frames of at most ``threads.SERIAL_MAX_PIXELS`` pixels (on one thread) hand a helper
    thread the later candidates that the stream's previous frame drew too (prepared, at least
    ``warp_ahead.WARP_AHEAD_MIN_POINTS`` points), which it warps and crack-filters while the
    adaptive loop works on the first view, so that the loop mostly finds them done
    (:mod:`presim.synthesis.warp_ahead`); frames below ``composite.TILED_MIN_PIXELS`` do so when it
    measures faster than all numba threads (``threads.FrameModeChooser``, per camera stream and
    size). The images do not depend on it; it uses the core such a frame leaves idle."""
    batch_views: int = 3
    """``backend="torch_batch"``: :meth:`Renderer.render_batch` renders every frame from this many
    of its selected views, all frames in one batch (no adaptive loop; later views fill holes only)."""
    batch_threads: int = 0
    """numba backend: :meth:`Renderer.render_batch` spreads its frames over this many threads, each
    rendering whole frames with the serial, GIL-free twins of the parallel kernels (same images as
    :meth:`Renderer.render`); 1 = one frame after another; 0 = auto: numba's thread count, or for
    frames that warp views ahead (``warp_ahead``) one frame after another when that measures faster
    (``Renderer.batch_mode`` says which ran)."""
    # ---- photometric correction (presim/synthesis/photometric.py, `presim photometric`) ----
    use_photometric: bool = True
    """Map every capture frame to one output exposure with ``scene.photometric`` when present
    (applied to the frame's pixels when its view is prepared and cached with it: no per-frame cost;
    any model: gain/bias, 3x3 affine, vignetting)."""
    exposure_frame: str | None = None
    """Output exposure: None = the capture's mean exposure (vignetting removed); a frame id = match
    that frame's (its transform, and its vignetting put back on the output when calibrated)."""
    # ---- multi-view blending (presim/synthesis/blend.py) ----
    blend: bool = False
    """Blend, per pixel, the views that agree with the front surface (ULR weights, feathered
    seams) instead of keeping the winning view's colour. Off by default (it changes the image; the
    default is the thesis's pipeline); with sharpness and photometric correction it costs +10 to
    +17 % CPU per frame at 640x480 (``benchmarks/bench_render.py --compare-blend``,
    docs/evaluation.md). The views the adaptive loop warped are reused, not warped again (numba
    backend: their front surface comes out of the crack pass, ``Workspace.front``)."""
    blend_views: int = 4
    """Blend among this many views: those the adaptive loop warped, in order, then the remaining
    selected candidates."""
    blend_depth_tol: float = 0.05
    """A view is blended at a pixel when its depth is within this fraction of the front surface's."""
    blend_feather_px: float = 8.0
    """Views fade in over this many pixels from the border of their coverage."""
    blend_penalty_eps: float = 0.05
    """Added to a view's angle + resolution penalty (radians) before inverting it to a weight:
    larger = more uniform averaging."""
    # ---- sharpness-aware views (presim/synthesis/sharpness.py) ----
    sharpness: bool = False
    """Prefer sharp capture frames: blurred candidates move behind sharp ones in the warp order and
    get lower blend weights (re-blur score, presim/capture/sharpness.py)."""
    sharpness_gamma: float = 2.0
    """Blend weight factor ``(score / best candidate's score) ** sharpness_gamma``."""
    blur_demote_frac: float = 0.85
    """Candidates scoring below this fraction of the best candidate are warped last."""

    def __post_init__(self) -> None:
        checks = [
            (self.num_layers >= 1, f"num_layers must be >= 1, got {self.num_layers}"),
            (self.selection in SELECTION_MODES, f"selection must be one of {SELECTION_MODES}"),
            (self.fixed_views >= 0, "fixed_views must be >= 0"),
            (self.max_candidates >= 1, "max_candidates must be >= 1"),
            (self.crack_filter in CRACK_FILTERS, f"crack_filter must be one of {CRACK_FILTERS}"),
            (self.hole_dilation_px >= 0, "hole_dilation_px must be >= 0"),
            (self.backend in BACKENDS, f"backend must be one of {BACKENDS}"),
            (self.max_views >= 1, "max_views must be >= 1"),
            (self.crack_kernel_px >= 1 and self.crack_kernel_px % 2 == 1, "crack_kernel_px must be odd"),
            (self.view_order in VIEW_ORDERS, f"view_order must be one of {VIEW_ORDERS}"),
            (self.overlap_stride_px >= 1, "overlap_stride_px must be >= 1"),
            (self.fill_method in FILL_METHODS, f"fill_method must be one of {FILL_METHODS}"),
            (self.fill_kernel in FILL_KERNELS, f"fill_kernel must be one of {FILL_KERNELS}"),
            (self.cache_mb > 0, "cache_mb must be > 0"),
            (self.max_zoom > 0, "max_zoom must be > 0"),
            (0.0 <= self.next_view_fill_frac <= 1.0, "next_view_fill_frac must be in [0, 1]"),
            (0 <= self.lod_levels <= 8, "lod_levels must be in [0, 8]"),
            (self.lod_max_footprint > 0, "lod_max_footprint must be > 0"),
            (self.lod_depth_tol >= 0, "lod_depth_tol must be >= 0"),
            (self.reuse_move_m >= 0 and self.reuse_turn_deg >= 0, "reuse_move_m / reuse_turn_deg must be >= 0"),
            (self.time_budget_ms >= 0, "time_budget_ms must be >= 0"),
            (0.0 <= self.min_view_gain < 1.0, "min_view_gain must be in [0, 1)"),
            (self.threads >= 0, "threads must be >= 0"),
            (self.batch_views >= 1, "batch_views must be >= 1"),
            (self.batch_threads >= 0, "batch_threads must be >= 0"),
            (self.blend_views >= 1, "blend_views must be >= 1"),
            (0.0 < self.blend_depth_tol < 1.0, "blend_depth_tol must be in (0, 1)"),
            (self.blend_feather_px >= 1.0, "blend_feather_px must be >= 1"),
            (self.blend_penalty_eps > 0.0, "blend_penalty_eps must be > 0"),
            (self.sharpness_gamma >= 0.0, "sharpness_gamma must be >= 0"),
            (0.0 <= self.blur_demote_frac <= 1.0, "blur_demote_frac must be in [0, 1]"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"RenderConfig: {msg}")

    def frame_config(self) -> FrameConfig:
        """The knobs of the per-frame core (:func:`presim.synthesis.core.synthesize_frame`)."""
        return FrameConfig(
            view=ViewImageConfig(near_m=self.near_m, crack_filter=self.crack_filter,
                                 crack_kernel_px=self.crack_kernel_px, packed_cracks=self.packed_cracks,
                                 masked_warp=self.masked_warp),
            fixed_views=self.fixed_views, max_views=self.max_views, stop_hole_frac=self.stop_hole_frac,
            big_hole_px=self.big_hole_px, hole_dilation_px=self.hole_dilation_px,
            next_view_fill_frac=self.next_view_fill_frac, fill_holes=self.fill_holes,
            fill_method=self.fill_method, fill_kernel=self.fill_kernel, time_budget_ms=self.time_budget_ms,
            min_view_gain=self.min_view_gain)

    def lod_config(self) -> LodConfig:
        """The level-of-detail knobs (:mod:`presim.synthesis.lod`)."""
        return LodConfig(self.lod_levels, self.lod_max_footprint, self.lod_depth_tol)


@dataclass
class RenderStats:
    """What the last :meth:`Renderer.render` did (for benchmarks and evaluation)."""

    views: list[int] = field(default_factory=list)
    """Scene frame indices warped, in order."""
    selection: Selection | None = None
    hole_frac_per_view: list[float] = field(default_factory=list)
    """Hole fraction after each merged view."""
    ms: dict[str, float] = field(default_factory=dict)
    """Milliseconds per stage (keys: STAGES)."""
    skipped: list[int] = field(default_factory=list)
    """Candidates left when the adaptive loop stopped because none of their grid points lands in a
    big hole."""
    lod_levels: list[int] = field(default_factory=list)
    """Pyramid level used for each warped view (0 = all points)."""
    reused_selection: bool = False
    """The selection was the previous frame's (temporal coherence)."""
    batch_views: list[list[int]] = field(default_factory=list)
    """After :meth:`Renderer.render_batch`: the views of every frame of the batch."""
    frame_mode: str | None = None
    """Frames that may run either on all numba threads or on one with views warped ahead
    (``threads.FrameModeChooser``): ``"threads"`` or ``"ahead"``; None for other frames."""
    frame_mode_chosen: bool = False
    """``frame_mode`` came from the stream's chooser (False: the frame had no view to warp ahead and
    used all threads; such frames are not timed for the choice)."""


class _WarpCapture:
    """Front surface of every view the adaptive loop warps, kept for blending so that blending
    does not warp those views again (numba backend: the view image writes it into the blend's
    stacks through ``Workspace.front`` from the same pass that reads the warped layers for the
    crack mask, :func:`~presim.synthesis.composite.filtered_composite_packed`; other backends
    keep no layers and blending warps the view itself)."""

    def __init__(self, stacks: dict, feather_px: float = 8.0) -> None:
        self._stacks = stacks  # the blend's per-view stacks: slot i = the i-th warped view
        self._feather_px = feather_px
        self._ids: list[int] = []

    def wrap(self, get_view, view_image, max_views: int):
        """``(get_view, view_image)`` for one frame's loop that record the front surfaces of the
        first ``max_views`` warped views (the loop calls ``get_view(id)`` right before warping it)
        straight into the blend's stacks (:func:`~presim.synthesis.blend.blend_stacks`)."""
        self._ids = []
        current: list[int] = []

        def get_view_rec(idx: int):
            current[:] = [int(idx)]
            return get_view(idx)

        def view_image_rec(view, T_cam_world, K, config, replace, workspace):
            n = len(self._ids)
            want = bool(current) and n < max_views and hasattr(workspace, "front")
            if want:  # the numba backend writes the front surface while it reads the layers
                d, c, _ = blend_stacks(self._stacks, max_views, K.height, K.width, self._feather_px)
                workspace.front = (d[n], c[n])
            try:
                img = view_image(view, T_cam_world, K, config, replace, workspace)
            finally:
                if want:
                    workspace.front = None
            lay = getattr(workspace, "layers", None)
            if want and isinstance(lay, LayeredImage):
                self._ids.append(current[0])
            current.clear()
            return img

        return get_view_rec, view_image_rec

    def get(self, view_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The recorded ``(depth, color)`` of ``view_id`` in this frame, or None."""
        try:
            n = self._ids.index(int(view_id))
        except ValueError:
            return None
        return self._stacks["d"][n], self._stacks["c"][n]


class _Scratch:
    """Buffers one rendering thread reuses across views and frames: the numba warp buffers, the
    blend's per-view stacks and the loop's warps kept for blending."""

    def __init__(self, feather_px: float):
        self.workspace = Workspace()
        self.blend_stacks: dict = {}
        self.warp_capture = _WarpCapture(self.blend_stacks, feather_px)
        self._ahead: WarpAhead | None = None

    @property
    def ahead(self) -> WarpAhead:
        """The helper thread that warps later candidates ahead (started on first use)."""
        if self._ahead is None:
            self._ahead = WarpAhead()
        return self._ahead


@dataclass
class _Stream:
    """What one camera stream carries from frame to frame: the previous frame's pose, intrinsics and
    view selection (temporal reuse, ``RenderConfig.reuse_move_m``)."""

    prev: tuple[np.ndarray, Intrinsics, Selection] | None = None
    views_drawn: tuple[int, ...] = ()
    """The views the previous frame's adaptive loop warped, in order (warped ahead this frame)."""
    modes: dict = field(default_factory=dict)
    """(width, height) -> :class:`~presim.synthesis.threads.FrameModeChooser`: how frames of that size
    render fastest (all numba threads, or one thread with views warped ahead)."""


class Renderer:
    """Renders RGB-D images of a scene at arbitrary poses and intrinsics from its captured views."""

    def __init__(self, scene: Scene, config: RenderConfig = RenderConfig()):
        self.scene = scene
        self.config = config
        T = scene.T_world_cam
        self._centres = T[:, :3, 3].copy()
        self._dirs = T[:, :3, 2] / np.linalg.norm(T[:, :3, 2], axis=1, keepdims=True)
        self._hfov_deg = np.array([K.hfov_deg for K in scene.intrinsics])
        self._focal_px = float(np.median([np.sqrt(K.fx * K.fy) for K in scene.intrinsics]))
        self._use_refined = bool(config.use_refined_depth and scene.depth_refined is not None)
        self._use_fused = bool(config.use_fused_depth and getattr(scene, "depth_fused", None) is not None)
        # Prepared views by key (idx at level 0, (idx, level) above), LRU bounded by cache_mb, and
        # optionally built ahead in a background thread (presim/synthesis/view_cache.py).
        self._cache = ViewCache(config.cache_mb * 2**20, background=config.prefetch and config.backend == "numba")
        self._grids: dict[int, np.ndarray] = {}
        self._grid_zsrc: dict[int, np.ndarray] = {}  # per view: its grid points' depth in the view (LOD)
        self.last = RenderStats()
        self._frame_config = config.frame_config()
        self._backend = get_backend(config.backend)
        self._device = self._backend.resolve_device(config.torch_device)
        self._lod = config.lod_config()
        self._src_focal = np.array([np.sqrt(K.fx * K.fy) for K in scene.intrinsics])
        self._T_cam_world_src: np.ndarray | None = None  # per view, built on first LOD use
        # Per camera stream (temporal reuse): render() is stream 0; render_batch() frame b is stream b.
        self._stream = _Stream()
        self._batch_streams: list[_Stream] = []
        # Per rendering thread: buffers reused across frames (render(): this one).
        self._scratch = _Scratch(config.blend_feather_px)
        self._thread_scratch = threading.local()
        self._batch_pool: ThreadPoolExecutor | None = None
        self._batch_pool_threads = 0
        self._batch_modes: dict[tuple[int, int, int], FrameModeChooser] = {}  # (B, W, H) -> chooser
        self.batch_mode: str | None = None
        """How the last numba :meth:`render_batch` rendered its frames: ``"threads"`` (on
        ``batch_threads`` threads) or ``"sequential"`` (one after another in the calling thread)."""
        # Photometric correction hook (presim/synthesis/photometric.py); None = colors as captured.
        # Applied to each capture frame's pixels when its view is prepared (cached with the view: no
        # per-frame cost); the core's per-view color_transform hook is left free.
        self._color_transform = self._source_correction = self._output_vignetting = None
        calib = getattr(scene, "photometric", None) if config.use_photometric else None
        if calib is not None:
            self._source_correction = SourceColorCorrection(calib, scene.frame_ids, scene.intrinsics,
                                                            config.exposure_frame)
            if calib.vignetting is not None and config.exposure_frame is not None:
                self._output_vignetting = OutputVignetting(calib, config.exposure_frame)
        self._blend_config = BlendConfig(config.blend_views, config.blend_depth_tol,
                                         penalty_eps=config.blend_penalty_eps,
                                         feather_px=config.blend_feather_px) if config.blend else None
        # warp ahead (RenderConfig.warp_ahead): the numba backend's warps, no blending (it keeps the
        # loop's warps), and a second core to run on
        self._use_warp_ahead = config.backend == "numba" and not config.blend and (os.cpu_count() or 1) >= 2
        # ... and the crack pass too where the frame would run the banded one (view_image_numba)
        self._ahead_crack = (config.crack_filter == "switching_median" and config.crack_kernel_px == 3
                             and config.packed_cracks and config.num_layers <= PACKED_MAX_LAYERS)
        self._sharpness = None  # sharpness-aware views (presim/synthesis/sharpness.py)
        if config.sharpness:
            self._sharpness = ViewSharpness(lambda v: self.scene.frames.load(v)[0], config.sharpness_gamma,
                                            config.blur_demote_frac)
        self._view_quality = None if self._sharpness is None else self._sharpness.quality  # blend factor

    # ---- per-view data (lazy, cached) ----------------------------------------------------------
    def _load_frame(self, idx: int, with_color: bool = True) -> tuple[np.ndarray, np.ndarray]:
        color, depth = self.scene.frames.load(idx)
        if self._source_correction is not None and with_color:  # photometric calibration
            color = self._source_correction(idx, color)
        if self._use_fused:
            depth = np.asarray(self.scene.depth_fused[idx])
        elif self._use_refined:
            depth = np.asarray(self.scene.depth_refined[idx])
        K = self.scene.intrinsics[idx]
        if depth.shape != (K.height, K.width) or depth.dtype != np.float32:
            raise SceneError(f"frame {self.scene.frame_ids[idx]}: depth must be float32 "
                             f"{K.height}x{K.width}, got {depth.dtype} {depth.shape}")
        return color, depth

    def _grid_from_depth(self, idx: int, depth: np.ndarray) -> np.ndarray:
        pts, _ = unproject_depth(self.scene.intrinsics[idx], depth, self.scene.T_world_cam[idx],
                                 stride=self.config.overlap_stride_px)
        # Stored per coordinate (an F-ordered (m, 3) array): the projection kernels read the rows of
        # its (3, m) transpose without a copy, and vectorize (presim/synthesis/grids.py).
        return np.asfortranarray(pts, np.float32)

    def grid_points(self, idx: int) -> np.ndarray:
        """(m, 3) float32 world points of view ``idx``'s sub-sampled valid depth (overlap test), stored
        per coordinate (F-ordered)."""
        g = self._grids.get(idx)
        if g is None:
            color, depth = self._load_frame(idx, with_color=False)
            g = self._grids[idx] = self._grid_from_depth(idx, depth)
            _unmap_pages(color)
            _unmap_pages(depth)
        return g

    def view_points(self, idx: int) -> ViewPoints:
        """The prepared points of view ``idx`` (numpy), built on first use."""
        v = self._view(idx)
        return v if isinstance(v, ViewPoints) else self._prepare(idx)

    def _prepare(self, idx: int) -> ViewPoints:
        color, depth = self._load_frame(idx)
        if idx not in self._grids:
            self._grids[idx] = self._grid_from_depth(idx, depth)
        view = prepare_view(color, depth, self.scene.intrinsics[idx], self.scene.T_world_cam[idx],
                            self.config.num_layers)
        _unmap_pages(color)
        _unmap_pages(depth)
        return view

    def _build_view(self, idx: int, level: int, parallel: bool = True):
        """View ``idx`` at ``level`` prepared and uploaded (``parallel=False``: serial kernels without
        the GIL, for the background thread; same result)."""
        view = self._prepare(idx) if level == 0 else self._prepare_level(idx, level, parallel)
        return self._backend.upload(view, self._device)

    def _view(self, idx: int, level: int = 0):
        return self._cache.get(idx if level == 0 else (idx, level), lambda: self._build_view(idx, level))

    def _prefetch(self, candidates: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics) -> None:
        """Have the background thread make candidates 2..``max_views`` that have no cached level yet
        ready for this target, each at the level of detail this target picks for it (the thread
        projects their grids itself). The first candidate is warped right away, so the main thread
        prepares it itself. Views cached at some level cost only dict lookups here: a per-frame job
        for every candidate (level tests in the thread) took the GIL from 128x96 frames often enough
        to make PointNav slower (docs/synthesis.md, "Views prepared ahead")."""
        cache, levels = self._cache, range(1, self._lod.levels + 1)
        cands = [int(v) for v in candidates[1:self.config.max_views]
                 if int(v) not in cache and not any((int(v), k) in cache for k in levels)]
        if cands:
            self._cache.ahead(lambda build_ahead: self._prepare_ahead(cands, T_cam_world, K, build_ahead))

    def _prepare_ahead(self, cands: list[int], T_cam_world: np.ndarray, K: Intrinsics, build_ahead) -> None:
        """Background thread: the views ``cands`` at this target's levels (serial kernels, no GIL)."""
        with serial_kernels():
            grids = FrameGrids(T_cam_world, K, self.grid_points)
            for v in cands:
                level = self._lod_level_fast(v, grids)
                build_ahead(v if level == 0 else (v, level), lambda v=v, level=level: self._build_view(v, level, False))

    def _prepare_level(self, idx: int, level: int, parallel: bool = True) -> ViewPoints:
        color, depth = self._load_frame(idx)
        if idx not in self._grids:
            self._grids[idx] = self._grid_from_depth(idx, depth)
        c, d, K = build_level(color, depth, self.scene.intrinsics[idx], level, self.config.lod_depth_tol, parallel)
        view = prepare_view(c, d, K, self.scene.T_world_cam[idx], self.config.num_layers)
        _unmap_pages(color)
        _unmap_pages(depth)
        return view

    def lod_level(self, idx: int, T_cam_world: np.ndarray, K: Intrinsics) -> int:
        """Pyramid level of view ``idx`` for a target camera (0 when ``lod_levels`` = 0)."""
        if self._lod.levels == 0:
            return 0
        if self._T_cam_world_src is None:
            self._T_cam_world_src = np.linalg.inv(self.scene.T_world_cam)
        r0 = footprint_ratio(self.grid_points(idx), self._T_cam_world_src[idx], float(self._src_focal[idx]),
                             T_cam_world, float(np.sqrt(K.fx * K.fy)), self.config.near_m, K)
        return choose_level(r0, self._lod)

    def _grid_zsrc_of(self, idx: int) -> np.ndarray:
        """float32 (m,) depth of view ``idx``'s grid points in the view itself (constant per view)."""
        z = self._grid_zsrc.get(idx)
        if z is None:
            if self._T_cam_world_src is None:
                self._T_cam_world_src = np.linalg.inv(self.scene.T_world_cam)
            z = transform_points(self._T_cam_world_src[idx], self.grid_points(idx))[:, 2]
            self._grid_zsrc[idx] = z = np.ascontiguousarray(z)
        return z

    def _lod_level_fast(self, idx: int, grids: FrameGrids) -> int:
        """:meth:`lod_level` from the frame's one projection of the grids (same result; mostly decided
        by counts, :meth:`FrameGrids.lod_level`)."""
        if self._lod.levels == 0:
            return 0
        return grids.lod_level(idx, self._grid_zsrc_of(idx), float(self._src_focal[idx]), self.config.near_m,
                               self._lod)

    def _grid_fill(self, idx: int, grids: FrameGrids, mask_flat: np.ndarray) -> float:
        """Target pixels that view ``idx``'s grid points landing on ``mask_flat`` stand for (one view at a
        time: the reference of the fill areas of :meth:`FrameGrids.hole_scores`, which the frames use)."""
        return grids.fill_area(idx, mask_flat, self._grid_zsrc_of(idx), float(self._src_focal[idx]),
                               self.config.near_m, float(self.config.overlap_stride_px))

    @property
    def cache_bytes(self) -> int:
        """Bytes held by the per-view point cache."""
        return self._cache.nbytes

    @property
    def view_cache(self) -> ViewCache:
        """The per-view point cache (:class:`~presim.synthesis.view_cache.ViewCache`: its size, and
        how many views the background thread built and the frames took)."""
        return self._cache

    # ---- public API ----------------------------------------------------------------------------
    def select(self, T_world_cam: np.ndarray, K: Intrinsics, grids: FrameGrids | None = None) -> Selection:
        """The ordered candidate views for a target camera (before the adaptive loop). ``grids``:
        the frame's grid projections to reuse (:class:`~presim.synthesis.grids.FrameGrids`)."""
        cfg = self.config
        if grids is None:
            grids = FrameGrids(invert(T_world_cam), K, self.grid_points)
        # Overlap fractions only for the views the adaptive loop may draw (max_views; with
        # fixed_views that many); the rest only need "overlaps at all" (same selection).
        n_exact = cfg.fixed_views if cfg.fixed_views > 0 else cfg.max_views
        return select_views(T_world_cam, K, self._centres, self._dirs, self._hfov_deg, self.grid_points,
                            cfg.selection, cfg.max_candidates, cfg.view_order, overlaps=grids.overlaps,
                            overlapping=grids.overlapping, exact_overlaps=n_exact)

    def render(self, T_world_cam: np.ndarray, K: Intrinsics) -> RGBD:
        """Synthesize color + depth at camera pose ``T_world_cam`` (4x4) with intrinsics ``K``."""
        if not isinstance(K, Intrinsics):
            raise ValueError(f"K must be presim.geometry.Intrinsics, got {type(K).__name__}")
        out, self.last = self._render_one(check_rigid(T_world_cam, "target pose T_world_cam"), K, self._stream,
                                          self._scratch)
        return out

    def _internal_K(self, K: Intrinsics) -> Intrinsics:
        """The intrinsics a target ``K`` is rendered at: ``K``, or beyond ``max_zoom`` a smaller image
        at the capture's sampling (upsampled to ``K`` after)."""
        scale = min(1.0, self.config.max_zoom * self._focal_px / np.sqrt(K.fx * K.fy))
        return K if scale >= 1.0 else K.scaled(max(1, round(K.width * scale)), max(1, round(K.height * scale)))

    def _render_one(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream, scratch: _Scratch
                    ) -> tuple[RGBD, RenderStats]:
        """One frame (pose already checked) of camera stream ``stream`` with the buffers ``scratch``."""
        K_in = self._internal_K(K)  # beyond max_zoom: rendered at the capture's sampling, then upsampled
        n_threads = frame_threads(K_in.width, K_in.height, self.config.threads)
        # A frame on one thread leaves a core idle: later candidates are warped ahead there, unless
        # this thread is one of several rendering at once (render_batch: serial kernels already).
        ahead = self._ahead_possible(K_in)
        chooser = None
        if ahead and n_threads > 1:
            # Either way works here (all numba threads, or one thread + the helper): measured per
            # stream and size (threads.FrameModeChooser; the images are the same). The frame picks
            # once it knows whether it has views to warp ahead (Renderer._render).
            chooser = stream.modes.get((K_in.width, K_in.height))
            if chooser is None:
                chooser = stream.modes[(K_in.width, K_in.height)] = FrameModeChooser(("threads", "ahead"))
        t0 = time.perf_counter()
        with numba_threads(n_threads):
            out, stats = self._render(T_world_cam, K_in, stream, scratch, ahead, chooser)
        if stats.frame_mode_chosen:  # time spent preparing views (a cold cache) is not the way's
            chooser.record(stats.frame_mode, (time.perf_counter() - t0) * 1e3 - stats.ms.get("load", 0.0))
        if K_in is K:
            return out, stats
        t = time.perf_counter()
        size = (K.width, K.height)
        color = cv2.resize(out.color, size, interpolation=cv2.INTER_LINEAR)
        depth = cv2.resize(out.depth_m, size, interpolation=cv2.INTER_NEAREST)
        valid = cv2.resize(out.valid.view(np.uint8), size, interpolation=cv2.INTER_NEAREST).view(bool)
        src = cv2.resize(out.source_view, size, interpolation=cv2.INTER_NEAREST)
        stats.ms["upsample"] = (time.perf_counter() - t) * 1e3
        return RGBD(color, depth, valid, src, K, T_world_cam, float(1.0 - valid.mean())), stats

    def _ahead_possible(self, K: Intrinsics) -> bool:
        """Whether a frame of size ``K`` rendered in this thread may warp views ahead on a helper
        thread (``RenderConfig.warp_ahead``; not inside :meth:`render_batch`'s frame threads)."""
        return (self.config.threads == 0 and self.config.warp_ahead and not serial_now() and self._use_warp_ahead
                and K.width * K.height < TILED_MIN_PIXELS)

    @property
    def _workspace(self) -> Workspace:
        """The warp buffers of :meth:`render` (tests)."""
        return self._scratch.workspace

    @property
    def _warp_capture(self) -> _WarpCapture:
        """The loop's warps kept for blending by :meth:`render` (tests)."""
        return self._scratch.warp_capture

    def _reusable(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream) -> Selection | None:
        """The stream's previous selection when the camera moved little (temporal coherence)."""
        cfg = self.config
        if stream.prev is None or cfg.reuse_move_m <= 0:
            return None
        T_prev, K_prev, sel = stream.prev
        # On Python floats: the numpy calls of the same tests took ~45 µs per frame in the render
        # loop (cold in the caches after the frame's kernels).
        a, b = T_world_cam[:3].tolist(), T_prev[:3].tolist()
        if K_prev != K or math.dist((a[0][3], a[1][3], a[2][3]), (b[0][3], b[1][3], b[2][3])) > cfg.reuse_move_m:
            return None
        # the angle of R_prev^T R: trace(R_prev^T R) = sum of the element-wise products
        cos = (sum(a[i][j] * b[i][j] for i in range(3) for j in range(3)) - 1.0) / 2.0
        if math.degrees(math.acos(min(max(cos, -1.0), 1.0))) > cfg.reuse_turn_deg:
            return None
        return sel

    def _render(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream, scratch: _Scratch,
                ahead: bool = False, chooser: FrameModeChooser | None = None) -> tuple[RGBD, RenderStats]:
        """One frame in the numba thread count the caller set. ``ahead``: later views may be warped
        ahead on the helper thread; with ``chooser`` (the caller runs all numba threads), the frame
        asks it after the selection whether to do so on one thread, or to use all threads."""
        t0 = time.perf_counter()
        T_cam_world = invert(T_world_cam)
        grids = FrameGrids(T_cam_world, K, self.grid_points)  # each grid projected once this frame
        levels: dict[int, int] = {}  # this frame's level of detail per view (asked once)

        def level_of(idx: int) -> int:
            lv = levels.get(idx)
            if lv is None:
                lv = levels[idx] = self._lod_level_fast(idx, grids) if self._lod.levels > 0 else 0
            return lv

        near = self.config.near_m
        sel = self._reusable(T_world_cam, K, stream)
        reused = sel is not None
        if sel is None:
            sel = self.select(T_world_cam, K, grids)
            if self._sharpness is not None:  # sharp views first (presim/synthesis/sharpness.py)
                p = self._sharpness.order(sel.view_idx)
                sel = dataclasses.replace(sel, view_idx=sel.view_idx[p], distance_m=sel.distance_m[p],
                                          angle_deg=sel.angle_deg[p], overlap_frac=sel.overlap_frac[p])
            stream.prev = (T_world_cam.copy(), K, sel)
        select_ms = (time.perf_counter() - t0) * 1e3

        def get_view(idx: int):
            return self._view(idx, level_of(idx))

        view_image = self._backend.view_image
        if self._blend_config is not None:  # keep the loop's warps for blending (no re-warp)
            get_view, view_image = scratch.warp_capture.wrap(get_view, view_image, self._blend_config.max_views)
        if self._cache.background:  # later candidates prepared while this frame runs
            self._prefetch(sel.view_idx, T_cam_world, K)
        # Warp ahead this frame's later candidates that the previous frame drew (a camera that moves
        # a little draws mostly the same views again; presim/synthesis/warp_ahead.py). Handed over
        # now, the helper thread wakes while the first view is warped (without the GIL).
        jobs = self._warp_ahead_jobs(sel.view_idx, level_of, stream.views_drawn) if ahead else []
        mode, chosen = None, False
        if chooser is not None:
            # Nothing to warp ahead: all threads, untimed (one thread would leave a core idle, and
            # the frame says nothing about which way is faster).
            mode, chosen = (chooser.pick(), True) if jobs else ("threads", False)
            if mode != "ahead":
                jobs = []
        if jobs:
            scratch.ahead.start(jobs, T_cam_world, K, near, crack=self._ahead_crack)
            scratch.workspace.ahead = scratch.ahead.take
        try:
            with numba_threads(1) if mode == "ahead" else contextlib.nullcontext():
                res = synthesize_frame(sel.view_idx, T_cam_world, K, self._frame_config,
                                       view_image, get_view, self.grid_points, scratch.workspace,
                                       color_transform=self._color_transform,
                                       blend=self._blend_hook(T_world_cam, T_cam_world, K, sel.view_idx, scratch),
                                       next_view=lambda ids, big, need, frac: grids.next_view(
                                           ids, big, self._grid_zsrc_of, lambda v: float(self._src_focal[v]),
                                           near, float(self.config.overlap_stride_px), need, frac))
        finally:
            if jobs:
                scratch.ahead.stop()
                scratch.workspace.ahead = None
        res.ms["select"] += select_ms
        stream.views_drawn = tuple(res.views)
        stats = RenderStats(views=res.views, selection=sel, hole_frac_per_view=res.hole_frac_per_view,
                            ms=res.ms, skipped=res.skipped, lod_levels=[levels.get(v, 0) for v in res.views],
                            reused_selection=reused, frame_mode=mode, frame_mode_chosen=chosen)
        color = res.color if self._output_vignetting is None else self._output_vignetting(res.color, K)
        return RGBD(color, res.depth_m, res.valid, res.source_view, K, T_world_cam, res.hole_frac), stats

    def _warp_ahead_jobs(self, candidates: np.ndarray, level_of: Callable[[int], int],
                         drawn_before: tuple[int, ...]) -> list:
        """The views to warp ahead: those of candidates 2..``max_views`` (or ``fixed_views``; the
        later views the adaptive loop may draw) that the stream's previous frame drew, first or
        later, in candidate order, at this frame's level of detail (:mod:`~presim.synthesis.
        warp_ahead`). Left out: views not prepared at that level yet (left to the loop and the view
        cache's background thread) and views of fewer than ``WARP_AHEAD_MIN_POINTS`` points."""
        if not drawn_before:
            return []
        cfg = self.config
        n = cfg.fixed_views if cfg.fixed_views > 0 else cfg.max_views
        before = set(drawn_before)
        jobs = []
        for c in candidates[1:n]:
            c = int(c)
            if c not in before:
                continue
            level = level_of(c)
            view = self._cache.peek(c if level == 0 else (c, level))
            if view is not None and len(view.xyz_world) >= WARP_AHEAD_MIN_POINTS:
                jobs.append(view)
        return jobs

    def _blend_hook(self, T_world_cam: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics, candidates,
                    scratch: _Scratch):
        """The core's ``blend`` hook for one target camera (None when blending is off): blends the
        views the loop warped, then the remaining selected candidates, up to ``blend_views``."""
        if self._blend_config is None:
            return None
        near = self.config.near_m

        def front_image(v: int, depth_out: np.ndarray, color_out: np.ndarray) -> None:
            got = scratch.warp_capture.get(v)
            if got is not None:  # the loop warped it already (usually into this very slot)
                if not np.shares_memory(got[0], depth_out):
                    np.copyto(depth_out, got[0])
                    np.copyto(color_out, got[1])
                return
            view = self._view(v, self.lod_level(v, T_cam_world, K) if self._lod.levels > 0 else 0)
            if isinstance(view, ViewPoints):
                front_image_points(view, T_cam_world, K, near, depth_out, color_out)
                return
            img = self._backend.view_image(view, T_cam_world, K, self._frame_config.view, None, Workspace())
            depth_out[:] = img.depth_m
            color_out[:] = img.color

        def run(views, color, depth, source):
            views = list(views) + [int(v) for v in candidates if int(v) not in views]
            return blend_frame(views, color, depth, source, T_world_cam, K, self._blend_config, front_image,
                               lambda v: self._centres[v], self._view_quality, self._color_transform,
                               buffers=scratch.blend_stacks)

        return run

    def render_batch(self, T_world_cams: np.ndarray, K: Intrinsics) -> list[RGBD]:
        """Render B poses (B, 4, 4) with the same intrinsics (per-view data is shared).

        With ``backend="torch_batch"`` all B frames are rendered in one batch on torch (CUDA when
        present, else CPU; :mod:`presim.synthesis.batch_torch`: ``batch_views`` views per frame, no
        adaptive loop); ``last.ms`` then holds the batch's stage times. Other backends render the
        poses frame by frame, each exactly as :meth:`render` would: frame ``b`` of a batch continues
        camera stream ``b`` of the previous batch (the temporal reuse of the view selection,
        ``reuse_move_m``, applies per stream), and on the numba backend the frames are spread over
        ``batch_threads`` threads, or with ``batch_threads`` = 0 (auto) rendered one after another
        in this thread when that measures faster (:meth:`_render_threaded`, :attr:`batch_mode`);
        ``last`` holds the last frame's stats and every frame's views (``last.batch_views``)."""
        T = np.asarray(T_world_cams, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"T_world_cams must be (B, 4, 4), got {T.shape}")
        if not isinstance(K, Intrinsics):
            raise ValueError(f"K must be presim.geometry.Intrinsics, got {type(K).__name__}")
        T = np.stack([check_rigid(t, "target pose T_world_cam") for t in T]) if len(T) else T
        if self._backend.frame_batch is None or len(T) == 0:
            return self._render_threaded(T, K)
        if self.config.max_zoom * self._focal_px < np.sqrt(K.fx * K.fy):
            return self._render_threaded(T, K)  # zoomed-in targets: per frame (internal size differs)
        from presim.synthesis.batch_torch import BatchConfig

        cfg = self.config
        t0 = time.perf_counter()
        T_cw = np.stack([invert(t) for t in T])
        grids = [FrameGrids(t, K, self.grid_points) for t in T_cw]
        sels = [self.select(t, K, g) for t, g in zip(T, grids)]
        select_ms = (time.perf_counter() - t0) * 1e3

        def get_view(b: int, idx: int):
            level = self._lod_level_fast(idx, grids[b])
            return (idx, level), self._view(idx, level)

        bcfg = BatchConfig(cfg.batch_views, cfg.near_m, cfg.crack_filter, cfg.crack_kernel_px, cfg.fill_holes,
                           cfg.fill_method)
        ms: dict[str, float] = {}
        frames = self._backend.frame_batch([s.view_idx for s in sels], T_cw, K, bcfg, get_view, ms)
        ms["select"] = select_ms
        self.last = RenderStats(views=frames[-1].views, selection=sels[-1], ms=ms,
                                batch_views=[list(f.views) for f in frames])
        return [RGBD(f.color, f.depth_m, f.valid, f.source_view, K, t, f.hole_frac) for f, t in zip(frames, T)]

    def _render_threaded(self, T: np.ndarray, K: Intrinsics) -> list[RGBD]:
        """Frames of checked poses ``T`` (B, 4, 4), frame ``b`` in camera stream ``b``; on the numba
        backend on up to ``batch_threads`` threads.

        With ``RenderConfig.batch_threads`` = 0 (auto) and frames that may warp views ahead (below
        ``composite.TILED_MIN_PIXELS``, ``warp_ahead`` on), the batch is either spread over numba's
        thread count of threads, or rendered one frame after another in this thread, each frame
        with its later views warped ahead on the helper thread that uses the other core
        (:mod:`presim.synthesis.warp_ahead`): a :class:`~presim.synthesis.threads.FrameModeChooser`
        per batch size and frame size measures both and keeps the faster (time per frame, without
        view preparation). On the 2-core machine the second way won at 128x96 (PointNav), because
        the frame threads serialise on the GIL for each frame's Python stretches.

        Each thread renders whole frames with its own buffers and the serial twins of the parallel
        kernels, which release the GIL (:mod:`presim.synthesis.threads`), so that the threads overlap
        in the compiled stages; the per-view cache is shared (a view another thread is building is
        waited for, not built twice). Each frame equals what :meth:`render` gives for its stream:
        nothing a frame reads depends on which thread rendered it or on the other frames."""
        B = len(T)
        while len(self._batch_streams) < B:
            self._batch_streams.append(_Stream())
        streams = self._batch_streams
        n = self.batch_threads(B)
        chooser = None
        if n > 1 and self.config.batch_threads == 0 and self._ahead_possible(self._internal_K(K)):
            # Auto: the frames on threads, or one after another here, each with its later views
            # warped ahead on the helper thread: measured per batch size and frame size (the images
            # are the same either way; threads.FrameModeChooser).
            key = (B, K.width, K.height)
            chooser = self._batch_modes.get(key)
            if chooser is None:
                chooser = self._batch_modes[key] = FrameModeChooser(("threads", "sequential"))
            self.batch_mode = chooser.pick()
            if self.batch_mode == "sequential":
                n = 1
        else:
            self.batch_mode = "threads" if n > 1 else "sequential"
        t0 = time.perf_counter()
        if n <= 1:
            outs = [self._render_one(T[b], K, streams[b], self._scratch) for b in range(B)]
        else:
            if self._batch_pool is None or self._batch_pool_threads != n:
                if self._batch_pool is not None:
                    self._batch_pool.shutdown(wait=True)
                self._batch_pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="presim-frames")
                self._batch_pool_threads = n

            def frame(b: int) -> tuple[RGBD, RenderStats]:
                scratch = getattr(self._thread_scratch, "scratch", None)
                if scratch is None:
                    scratch = self._thread_scratch.scratch = _Scratch(self.config.blend_feather_px)
                with serial_kernels():
                    return self._render_one(T[b], K, streams[b], scratch)

            outs = list(self._batch_pool.map(frame, range(B)))
        if chooser is not None:  # per frame, without the time spent preparing views
            load_ms = sum(o[1].ms.get("load", 0.0) for o in outs)
            chooser.record(self.batch_mode, ((time.perf_counter() - t0) * 1e3 - load_ms) / B)
        if outs:  # the last frame's stats, and every frame's views
            self.last = dataclasses.replace(outs[-1][1], batch_views=[list(o[1].views) for o in outs])
        return [o[0] for o in outs]

    def batch_threads(self, batch: int) -> int:
        """Threads :meth:`render_batch` may use for ``batch`` frames rendered frame by frame: 1 unless
        the backend is numba; ``RenderConfig.batch_threads`` when > 0, else (auto) numba's thread
        count, never more than ``batch`` (auto may still render them one after another:
        :meth:`_render_threaded`, :attr:`batch_mode`)."""
        if self.config.backend != "numba" or batch <= 1:
            return 1
        n = self.config.batch_threads if self.config.batch_threads > 0 else numba.get_num_threads()
        return max(1, min(n, batch))
