"""The two configurations of the renderer: :class:`RenderConfig`, everything that may change the image, and
:class:`PerfConfig`, what never does (two renderers that differ only in it give the same pixels, tested)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RenderConfig", "PerfConfig", "SELECTION_MODES", "VIEW_ORDERS", "CRACK_FILTERS", "FILL_METHODS",
           "BACKENDS"]

SELECTION_MODES = ("adaptive", "distance", "angle")
VIEW_ORDERS = ("overlap", "distance")
CRACK_FILTERS = ("switching_median", "median", "none")
FILL_METHODS = ("auto", "telea", "pushpull")
BACKENDS = ("numba", "reference", "torch")


@dataclass(frozen=True)
class RenderConfig:
    """What the renderer computes: the thesis's pipeline (§3.4.2-3.4.4) plus the approximations measured in
    docs/synthesis.md."""

    num_layers: int = 4
    """L of layered warping (thesis: 4 is the quality/speed trade-off); 1 = plain DIBR z-buffer."""
    selection: str = "adaptive"
    """``"adaptive"`` (distance -> angle vs FOV -> overlap), ``"distance"`` or ``"angle"`` only."""
    fixed_views: int = 0
    """> 0: warp exactly this many selected views (no adaptive loop), e.g. 1, 2, 3 as Table 3.5."""
    max_candidates: int = 10
    """Size of the local group (top-k by camera-centre distance, eq. 3.5)."""
    view_order: str = "distance"
    """Warp order: ``"distance"`` (nearest first; better on the real capture) or ``"overlap"`` (largest first)."""
    max_views: int = 6
    """The adaptive loop draws from the first ``max_views`` selected views only."""
    hole_candidates: int = 20
    """The ring: where the completion stage ran, the loop goes on over this many further views by camera distance
    (within the FOV angle, overlapping the target) for the large holes left (docs/synthesis.md); 0 = off."""
    ring_max_views: int = 3
    """The ring warps at most this many views per frame."""
    ring_min_hole_frac: float = 0.04
    """The ring writes only holes of at least this fraction of the image, and a ring view must be predicted to fill
    that much: smaller holes are mostly missing geometry, which a distant view sees through to the background."""
    stop_hole_frac: float = 0.0005
    """The adaptive loop stops when the largest hole is at most this fraction of the image (154 px at 640x480)."""
    big_hole_px: int = 16
    """Holes of at least this many pixels are big: dilated, and the next view must land in them."""
    hole_dilation_px: int = 2
    """Big holes grow by this radius before the next view fills them (ghost contours)."""
    next_view_fill_frac: float = 0.0
    """Next view = first candidate whose grid puts >= 1 point and >= this fraction of the best count into the
    big holes. 0 = selection order; 1 = greedy coverage (within 0.1 dB of each other on the real capture)."""
    min_view_gain: float = 0.005
    """A further view must be predicted to fill at least this fraction of the image; 0 = the thesis's loop.
    0.005: 3.6 instead of 6.0 views per frame (apc, 640x480), within 0.04 dB / 0.0013 SSIM."""
    time_budget_ms: float = 0.0
    """> 0: no further view once the frame has taken this long (the fill still runs)."""
    overlap_stride_px: int = 8
    """Sampling interval of each view's grid for the overlap and hole-fill tests."""
    near_m: float = 0.01
    """Points closer than this to the target camera are dropped."""
    backward_color: bool = False
    """Colours sampled bilinearly in each pixel's source view (:mod:`presim.synthesis.resample`): +0.27 /
    +0.15 dB on the APC / TUM captures, ~1.6x the CPU of a 640x480 frame."""
    backward_depth_tol: float = 0.05
    """A bilinear tap counts when its source depth is within this fraction of the projected depth."""
    crack_filter: str = "switching_median"
    """``"switching_median"`` (eq. 3.9), ``"median"`` (plain) or ``"none"``."""
    crack_kernel_px: int = 3
    """N of the N x N (switching) median window."""
    fill_holes: bool = True
    """Fill pixels no view covers (they stay False in ``RGBD.valid``); False leaves them 0."""
    fill_method: str = "auto"
    """``"auto"``, ``"telea"`` or ``"pushpull"`` (:mod:`presim.synthesis.fill`). ``"auto"``: Telea up to 2 % holes,
    pull-push above; pull-push after the completion stage ran (the warped views have completed depth): leave-one-out
    on APC / TUM -0.07 / +0.02 dB against Telea there, at 16 % / 9 % less time per frame (docs/evaluation.md)."""
    fill_background_px: int = 0
    """> 0: known pixels this close to a hole and in front of its background do not feed the colour fill
    (:func:`presim.synthesis.fill.foreground_rim`)."""
    use_refined_depth: bool = True
    """Use ``scene.depth_refined`` (``presim refine``) when present, else the raw depth."""
    use_fused_depth: bool = False
    """Use ``scene.depth_fused`` (``presim fuse``) when present; wins over ``use_refined_depth``."""
    use_completed_depth: bool = True
    """Pixels no measured depth covers take the warped views' completed depth (``scene.depth_completed``,
    ``presim complete``) when the scene has it, before the fill."""
    max_zoom: float = 1.0
    """A target sampling the scene more densely than this x the capture is rendered smaller and upsampled
    (one-pixel splats cannot cover a surface magnified ~1.5x); at 1280x720 within 0.2 dB of 1.3, 2-5x faster."""
    lod_levels: int = 3
    """Coarsest pyramid level of a view's points (2x2 depth-aware pooling per level); 0 = every point."""
    lod_max_footprint: float = 1.0
    """Target pixels one point of the chosen level may cover (median over the view's grid)."""
    lod_depth_tol: float = 0.02
    """Relative depth band of the front surface pooled together in a 2x2 block."""
    reuse_move_m: float = 0.01
    """A frame whose camera moved at most this far (and turned at most ``reuse_turn_deg``) since its stream's
    previous frame reuses that selection; 0 disables."""
    reuse_turn_deg: float = 1.0
    """Rotation bound of the selection reuse, degrees."""
    smooth_sigma_px: float | None = None
    """Gaussian reconstruction filter of the output colour (:mod:`presim.imaging.gaussian`), sigma in pixels
    at the capture's sampling (scaled with the output focal length); None = the scene's fitted value
    (``scene.render_filter_sigma_px``, ``presim fit-filter``), none when it has none; 0 = off."""
    use_photometric: bool = True
    """Map every capture frame to one output exposure with ``scene.photometric`` when present."""
    exposure_frame: str | None = None
    """Output exposure of a calibrated scene: that frame's; None = predicted or the capture's mean."""
    predict_exposure: bool = True
    """The image takes the exposure of the capture frames it is made of, weighted by their share of its
    pixels; False = the capture's mean (4.6 dB worse on a held-out capture)."""
    blend: bool = False
    """Blend the views that agree with the front surface per pixel (ULR weights; +10-17 % CPU at 640x480)."""
    blend_views: int = 4
    """Blend among this many views: those the loop warped, in order, then the other candidates."""
    blend_depth_tol: float = 0.05
    """A view is blended at a pixel when its depth is within this fraction of the front surface's."""
    blend_feather_px: float = 8.0
    """Views fade in over this many pixels from the border of their coverage."""
    blend_penalty_eps: float = 0.05
    """Added to a view's angle + resolution penalty (radians) before inverting it to a weight."""
    sharpness: bool = False
    """Prefer sharp capture frames: blurred candidates are warped last and weigh less in blending."""
    sharpness_gamma: float = 2.0
    """Blend weight factor ``(score / best candidate's score) ** sharpness_gamma``."""
    blur_demote_frac: float = 0.85
    """Candidates scoring below this fraction of the best candidate are warped last."""

    def __post_init__(self) -> None:
        checks = [
            (self.hole_candidates >= 0, "hole_candidates must be >= 0"),
            (0.0 <= self.ring_min_hole_frac <= 1.0, "ring_min_hole_frac must be in [0, 1]"),
            (self.ring_max_views >= 0, "ring_max_views must be >= 0"),
            (self.num_layers >= 1, f"num_layers must be >= 1, got {self.num_layers}"),
            (self.selection in SELECTION_MODES, f"selection must be one of {SELECTION_MODES}"),
            (self.fixed_views >= 0, "fixed_views must be >= 0"),
            (self.max_candidates >= 1, "max_candidates must be >= 1"),
            (self.view_order in VIEW_ORDERS, f"view_order must be one of {VIEW_ORDERS}"),
            (self.max_views >= 1, "max_views must be >= 1"),
            (self.big_hole_px >= 1 and self.hole_dilation_px >= 0, "big_hole_px must be >= 1, hole_dilation_px >= 0"),
            (0.0 <= self.next_view_fill_frac <= 1.0, "next_view_fill_frac must be in [0, 1]"),
            (0.0 <= self.min_view_gain < 1.0, "min_view_gain must be in [0, 1)"),
            (self.time_budget_ms >= 0, "time_budget_ms must be >= 0"),
            (self.overlap_stride_px >= 1, "overlap_stride_px must be >= 1"),
            (0.0 < self.backward_depth_tol < 1.0, "backward_depth_tol must be in (0, 1)"),
            (self.crack_filter in CRACK_FILTERS, f"crack_filter must be one of {CRACK_FILTERS}"),
            (self.crack_kernel_px >= 1 and self.crack_kernel_px % 2 == 1, "crack_kernel_px must be odd"),
            (self.fill_method in FILL_METHODS, f"fill_method must be one of {FILL_METHODS}"),
            (self.fill_background_px >= 0, "fill_background_px must be >= 0"),
            (self.max_zoom > 0, "max_zoom must be > 0"),
            (self.smooth_sigma_px is None or 0.0 <= self.smooth_sigma_px <= 8.0, "smooth_sigma_px must be in [0, 8]"),
            (0 <= self.lod_levels <= 8, "lod_levels must be in [0, 8]"),
            (self.lod_max_footprint > 0 and self.lod_depth_tol >= 0, "lod_max_footprint > 0, lod_depth_tol >= 0"),
            (self.reuse_move_m >= 0 and self.reuse_turn_deg >= 0, "reuse_move_m / reuse_turn_deg must be >= 0"),
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


@dataclass(frozen=True)
class PerfConfig:
    """How the renderer runs. None of these fields changes a pixel."""

    backend: str = "numba"
    """``"numba"``, ``"reference"`` (slow numpy, tests) or ``"torch"`` (CUDA when present)."""
    torch_device: str | None = None
    """Torch device (None: CUDA when available, else CPU)."""
    threads: int = 0
    """numba threads per frame: 0 = one up to ``numba_threads.SERIAL_MAX_PIXELS`` pixels, else all; > 0 that many."""
    warp_ahead: bool = True
    """Frames on one thread: a helper thread warps the later candidates the stream's previous frame drew
    (:mod:`presim.synthesis.warp_ahead`; 1.13x at 128x128 on the apc capture)."""
    cache_mb: float = 1024.0
    """Bound of the per-view point cache (LRU), MiB."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"PerfConfig: backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.threads < 0:
            raise ValueError("PerfConfig: threads must be >= 0")
        if not self.cache_mb > 0:
            raise ValueError("PerfConfig: cache_mb must be > 0")
