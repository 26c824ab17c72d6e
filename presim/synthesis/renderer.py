"""Renderer: the stateful component of view synthesis (thesis §3.4.2-3.4.4).

    Renderer(scene, RenderConfig(), PerfConfig()).render(T_world_cam, K) -> RGBD

Per frame: select the candidates (:mod:`select`), then :func:`presim.synthesis.pipeline.synthesize_frame` with
this renderer's :class:`_FrameViews`. Per scene: camera centres, axes and FOVs; per view, lazily, the prepared
points per level of detail (in the executor's cache) and a sub-sampled grid of world points."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from dataclasses import replace as dc_replace

import cv2
import numpy as np

from presim.capture.scene import Scene, SceneError
from presim.capture.store import unmap_pages
from presim.capture.sharpness import ViewSharpness
from presim.geometry import Intrinsics, check_rigid, invert, transform_points, unproject_depth
from presim.photometric.apply import OutputVignetting, SourceColorCorrection, predict_exposure
from presim.sensors.rgbd import RGBD
from presim.synthesis.blend import BlendConfig, blend_frame, blend_stacks, front_of_layers
from presim.synthesis.completion import CompletedPoints
from presim.synthesis.config import PerfConfig, RenderConfig
from presim.synthesis.execution import Executor
from presim.synthesis.grids import FrameGrids
from presim.synthesis.lod import LodConfig, build_level
from presim.synthesis.pipeline import STAGES, ViewImage, synthesize_frame
from presim.synthesis.resample import SourceImage, SourceStack, stack_sources
from presim.synthesis.select import Selection, ring_views, select_views
from presim.synthesis.warp import ViewPoints, prepare_view, warp_layers

__all__ = ["STAGES", "RenderConfig", "PerfConfig", "RenderStats", "Renderer"]


@dataclass
class RenderStats:
    """What the last :meth:`Renderer.render` did (benchmarks, evaluation)."""

    views: list[int] = field(default_factory=list)
    """Scene frame indices warped, in order."""
    selection: Selection | None = None
    hole_frac_per_view: list[float] = field(default_factory=list)
    """Hole fraction after each merged view."""
    ms: dict[str, float] = field(default_factory=dict)
    """Milliseconds per stage (keys: STAGES, plus "upsample" beyond ``max_zoom``)."""
    skipped: list[int] = field(default_factory=list)
    """Candidates left when the loop stopped because none can fill a big hole."""
    lod_levels: list[int] = field(default_factory=list)
    """Pyramid level used for each warped view (0 = all points)."""
    reused_selection: bool = False
    """The selection was the previous frame's (temporal coherence)."""
    completed: np.ndarray | None = None
    """bool (H, W): pixels covered by completed depth (None: the completion stage did not run)."""
    batch_views: list[list[int]] = field(default_factory=list)
    """After :meth:`Renderer.render_batch`: the views of every frame of the batch."""


@dataclass
class _Stream:
    """What one camera stream carries from frame to frame."""

    prev: tuple[np.ndarray, Intrinsics, Selection] | None = None
    """Pose, intrinsics and selection of the previous frame (selection reuse)."""
    views_drawn: tuple[int, ...] = ()
    """The views the previous frame warped, in order (warped ahead this frame)."""


class _FrameViews:
    """The views of one target camera as the pipeline sees them (:class:`~presim.synthesis.pipeline.FrameViews`)."""

    def __init__(self, r: Renderer, T_world_cam: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics,
                 grids: FrameGrids, sel: Selection):
        self.r, self.T_world_cam, self.T_cam_world, self.K, self.grids = r, T_world_cam, T_cam_world, K, grids
        self.candidates = [int(v) for v in sel.view_idx]
        self.kernels = r.executor.kernels
        self.smooth_sigma_px = r.smooth_sigma_px * float(np.sqrt(K.fx * K.fy)) / r._focal_px
        self.levels: dict[int, int] = {}
        self.fronts: list[int] = []  # views whose front surface the loop wrote into the blend stacks

    def level(self, v: int) -> int:
        """View ``v``'s pyramid level from the frame's one projection of the grids (reference: lod.footprint_ratio)."""
        lv = self.levels.get(v)
        if lv is None:
            r = self.r
            lv = self.levels[v] = self.grids.lod_level(v, r.grid_zsrc(v), float(r.src_focal[v]), r.config.near_m, r.lod)
        return lv

    def view_image(self, view_id: int, replace: np.ndarray | None) -> ViewImage:
        r = self.r
        t = time.perf_counter()
        view = r.view(view_id, self.level(view_id))
        load_ms = (time.perf_counter() - t) * 1e3
        front = None
        if r.blend_config is not None and r.perf.backend == "numba" and len(self.fronts) < r.blend_config.max_views:
            d, c, _ = blend_stacks(r.blend_buffers, r.blend_config.max_views, self.K.height, self.K.width,
                                   r.blend_config.feather_px)
            front = (d[len(self.fronts)], c[len(self.fronts)])
        img = r.executor.view_image(view, self.T_cam_world, self.K, r.config, replace, front)
        if front is not None:
            self.fronts.append(view_id)
        img.load_ms = load_ms
        return img

    def ring(self) -> list[int]:
        r = self.r
        return [int(v) for v in ring_views(self.T_world_cam, r.centres, r.dirs, r.hfov_deg, r.config.max_candidates,
                                           r.config.hole_candidates, self.grids.overlapping)]

    def completed_points(self, warped: list[int]) -> list[CompletedPoints]:
        r = self.r
        if not r.use_completed:
            return []
        return [CompletedPoints(v, p.xyz_world, p.rgb) for v in warped
                for p in [r.completed_view(v, self.level(v))] if len(p.xyz_world)]

    def next_view(self, pending: list[int], big_flat: np.ndarray, need_px: float | None, frac: float) -> int:
        r = self.r
        return self.grids.next_view(pending, big_flat, r.grid_zsrc, lambda v: float(r.src_focal[v]), r.config.near_m,
                                    float(r.config.overlap_stride_px), need_px, frac)

    def sources(self, warped: list[int]) -> SourceStack:
        r = self.r
        return stack_sources(warped, [r.view(v, self.level(v)).image for v in warped])

    def exposure(self, source: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        r = self.r
        if r.calib is None:
            return None
        counts = np.bincount(source.reshape(-1) + 1, minlength=len(r.scene) + 1)[1:]
        ids = np.flatnonzero(counts)
        rows = [r.calib_rows[v] for v in ids]
        keep = [k for k, row in enumerate(rows) if row >= 0]
        return predict_exposure(r.calib, np.array([rows[k] for k in keep], np.int64), counts[ids][keep])

    def blend(self, warped: list[int], color: np.ndarray, depth_m: np.ndarray, source: np.ndarray) -> np.ndarray:
        r = self.r
        views = list(warped) + [v for v in self.candidates if v not in warped]

        def front_image(v: int, depth_out: np.ndarray, color_out: np.ndarray) -> None:
            if v in self.fronts:  # the loop wrote it into its slot already
                n = self.fronts.index(v)
                d, c, _ = blend_stacks(r.blend_buffers, r.blend_config.max_views, self.K.height, self.K.width,
                                       r.blend_config.feather_px)
                if not np.shares_memory(d[n], depth_out):
                    np.copyto(depth_out, d[n])
                    np.copyto(color_out, c[n])
                return
            view = r.view(v, self.level(v))
            if isinstance(view, ViewPoints):
                lay = warp_layers(view, self.T_cam_world, self.K, r.config.near_m)
                front_of_layers(lay.depth_m, lay.color, depth_out, color_out)
                return
            img = r.executor.kernels.view_image(view, self.T_cam_world, self.K, r.config, None, r.executor.workspace)
            depth_out[:] = img.depth_m
            color_out[:] = img.color

        out, _ = blend_frame(views, color, depth_m, source, self.T_world_cam, self.K, r.blend_config, front_image,
                             lambda v: r.centres[v], r.view_quality, r.executor.kernels.blend,
                             r.blend_buffers)
        return out


class Renderer:
    """Renders RGB-D images of a scene at arbitrary poses and intrinsics from its captured views."""

    def __init__(self, scene: Scene, config: RenderConfig = RenderConfig(), perf: PerfConfig = PerfConfig()):
        if not isinstance(config, RenderConfig) or not isinstance(perf, PerfConfig):
            raise TypeError("Renderer(scene, RenderConfig, PerfConfig)")
        self.scene, self.config, self.perf = scene, config, perf
        T = scene.T_world_cam
        self.centres = T[:, :3, 3].copy()
        self.dirs = T[:, :3, 2] / np.linalg.norm(T[:, :3, 2], axis=1, keepdims=True)
        self.hfov_deg = np.array([K.hfov_deg for K in scene.intrinsics])
        self.src_focal = np.array([np.sqrt(K.fx * K.fy) for K in scene.intrinsics])
        self._focal_px = float(np.median(self.src_focal))
        self._T_cam_world_src = invert(T) if len(T) else T
        self._use_refined = bool(config.use_refined_depth and scene.depth_refined is not None)
        self._use_fused = bool(config.use_fused_depth and getattr(scene, "depth_fused", None) is not None)
        self.use_completed = bool(config.use_completed_depth and getattr(scene, "depth_completed", None) is not None)
        fitted = getattr(scene, "render_filter_sigma_px", None)
        self.smooth_sigma_px = float(config.smooth_sigma_px if config.smooth_sigma_px is not None else fitted or 0.0)
        """Sigma of the reconstruction filter at the capture's sampling (pixels; 0 = none)."""
        self._grids: dict[int, np.ndarray] = {}
        self._grid_zsrc: dict[int, np.ndarray] = {}
        self.lod = LodConfig(config.lod_levels, config.lod_max_footprint, config.lod_depth_tol)
        self.executor = Executor(perf, config)
        self.last = RenderStats()
        self._stream = _Stream()
        self._batch_streams: list[_Stream] = []
        self._source_correction = self._output_vignetting = None
        calib = self.calib = getattr(scene, "photometric", None) if config.use_photometric else None
        rows = {f: i for i, f in enumerate(calib.frame_ids)} if calib is not None else {}
        self.calib_rows = [rows.get(f, -1) for f in scene.frame_ids]  # -1: not calibrated, keeps its colours
        if calib is not None:  # applied to each frame's pixels when its view is prepared (cached)
            self._source_correction = SourceColorCorrection(calib, scene.frame_ids, scene.intrinsics,
                                                            config.exposure_frame)
            if calib.vignetting is not None and config.exposure_frame is not None:
                self._output_vignetting = OutputVignetting(calib, config.exposure_frame)
        self.blend_config = None if not config.blend else BlendConfig(
            config.blend_views, config.blend_depth_tol, penalty_eps=config.blend_penalty_eps,
            feather_px=config.blend_feather_px)
        self.blend_buffers: dict = {}
        self._sharpness = None
        if config.sharpness:
            self._sharpness = ViewSharpness(lambda v: self.scene.frames.load(v)[0], config.sharpness_gamma,
                                            config.blur_demote_frac)
        self.view_quality = None if self._sharpness is None else self._sharpness.quality

    # ---- per-view data (lazy, cached) ----------------------------------------------------------
    def _load_frame(self, idx: int, with_color: bool = True) -> tuple[np.ndarray, np.ndarray]:
        color, depth = self.scene.frames.load(idx)
        if self._source_correction is not None and with_color:
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
        # per coordinate (F-ordered): the projection kernels read rows of its transpose without a copy
        return np.asfortranarray(pts, np.float32)

    def grid_points(self, idx: int) -> np.ndarray:
        """(m, 3) float32 world points of view ``idx``'s sub-sampled valid depth (F-ordered)."""
        g = self._grids.get(idx)
        if g is None:
            color, depth = self._load_frame(idx, with_color=False)
            g = self._grids[idx] = self._grid_from_depth(idx, depth)
            unmap_pages(color)
            unmap_pages(depth)
        return g

    def grid_zsrc(self, idx: int) -> np.ndarray:
        """float32 (m,) depth of view ``idx``'s grid points in the view itself."""
        z = self._grid_zsrc.get(idx)
        if z is None:
            z = transform_points(self._T_cam_world_src[idx], self.grid_points(idx))[:, 2]
            self._grid_zsrc[idx] = z = np.ascontiguousarray(z)
        return z

    def _prepare(self, idx: int, level: int, completed: bool = False) -> ViewPoints:
        """View ``idx``'s points at ``level``; with ``completed`` those of its completed depth (one layer)."""
        color, depth = self._load_frame(idx)
        if completed:
            depth = np.asarray(self.scene.depth_completed[idx])
        elif idx not in self._grids:
            self._grids[idx] = self._grid_from_depth(idx, depth)
        K = self.scene.intrinsics[idx]
        c, d = color, depth
        if level > 0:
            c, d, K = build_level(color, depth, K, level, self.config.lod_depth_tol)
        image = None
        if self.config.backward_color and not completed:  # kept with the points (the map's pages are dropped below)
            image = SourceImage(np.array(c, np.uint8), np.array(d, np.float32), K, self._T_cam_world_src[idx])
        view = prepare_view(c, d, K, self.scene.T_world_cam[idx], 1 if completed else self.config.num_layers, image)
        unmap_pages(color)
        unmap_pages(depth)
        return view

    def view(self, idx: int, level: int = 0):
        """View ``idx`` prepared at ``level`` in the backend's form (cached)."""
        key = idx if level == 0 else (idx, level)
        return self.executor.cache.get(key, lambda: self.executor.kernels.upload(self._prepare(idx, level)))

    def completed_view(self, idx: int, level: int = 0) -> ViewPoints:
        """The points of view ``idx``'s completed depth at ``level`` (cached, numpy on every backend)."""
        return self.executor.cache.get((idx, level, "completed"), lambda: self._prepare(idx, level, completed=True))

    # ---- public API ----------------------------------------------------------------------------
    def select(self, T_world_cam: np.ndarray, K: Intrinsics, grids: FrameGrids | None = None) -> Selection:
        """The ordered candidate views for a target camera (before the adaptive loop)."""
        cfg = self.config
        if grids is None:
            grids = FrameGrids(invert(T_world_cam), K, self.grid_points)
        n_exact = cfg.fixed_views if cfg.fixed_views > 0 else cfg.max_views
        sel = select_views(T_world_cam, K, self.centres, self.dirs, self.hfov_deg, self.grid_points, cfg.selection,
                           cfg.max_candidates, cfg.view_order, overlaps=grids.overlaps, overlapping=grids.overlapping,
                           exact_overlaps=n_exact)
        if self._sharpness is not None:  # sharp views first
            p = self._sharpness.order(sel.view_idx)
            sel = dc_replace(sel, view_idx=sel.view_idx[p], distance_m=sel.distance_m[p], angle_deg=sel.angle_deg[p],
                             overlap_frac=sel.overlap_frac[p])
        return sel

    def render(self, T_world_cam: np.ndarray, K: Intrinsics) -> RGBD:
        """Synthesize colour + depth at camera pose ``T_world_cam`` (4x4) with intrinsics ``K``."""
        K = _check_K(K)
        out, self.last = self._render_one(check_rigid(T_world_cam, "target pose T_world_cam"), K, self._stream)
        return out

    def render_batch(self, T_world_cams: np.ndarray, K: Intrinsics) -> list[RGBD]:
        """Render B poses (B, 4, 4) with the same intrinsics; frame ``b`` continues camera stream ``b``
        of the previous batch (selection reuse per stream). ``last`` holds the last frame's stats and
        every frame's views (``last.batch_views``)."""
        T = np.asarray(T_world_cams, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"T_world_cams must be (B, 4, 4), got {T.shape}")
        K = _check_K(K)
        T = np.stack([check_rigid(t, "target pose T_world_cam") for t in T]) if len(T) else T
        while len(self._batch_streams) < len(T):
            self._batch_streams.append(_Stream())
        outs = [self._render_one(T[b], K, self._batch_streams[b]) for b in range(len(T))]
        if outs:
            self.last = outs[-1][1]
            self.last.batch_views = [list(o[1].views) for o in outs]
        return [o[0] for o in outs]

    def close(self) -> None:
        """Stop the executor's helper threads (they also end with the process)."""
        self.executor.close()

    # ---- one frame -----------------------------------------------------------------------------
    def _internal_K(self, K: Intrinsics) -> Intrinsics:
        """``K``, or beyond ``max_zoom`` a smaller image at the capture's sampling (upsampled after)."""
        scale = min(1.0, self.config.max_zoom * self._focal_px / np.sqrt(K.fx * K.fy))
        return K if scale >= 1.0 else K.scaled(max(1, round(K.width * scale)), max(1, round(K.height * scale)))

    def _render_one(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream) -> tuple[RGBD, RenderStats]:
        K_in = self._internal_K(K)
        with self.executor.frame(K_in):
            out, stats = self._render(T_world_cam, K_in, stream)
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

    def _render(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream) -> tuple[RGBD, RenderStats]:
        t0 = time.perf_counter()
        T_cam_world = invert(T_world_cam)
        grids = FrameGrids(T_cam_world, K, self.grid_points)  # each grid projected once this frame
        sel = self._reusable(T_world_cam, K, stream)
        reused = sel is not None
        if sel is None:
            sel = self.select(T_world_cam, K, grids)
            stream.prev = (T_world_cam.copy(), K, sel)
        frame = _FrameViews(self, T_world_cam, T_cam_world, K, grids, sel)
        select_ms = (time.perf_counter() - t0) * 1e3
        self._schedule(frame, stream)
        res = synthesize_frame(frame, T_cam_world, K, self.config)
        res.ms["select"] += select_ms
        stream.views_drawn = tuple(res.views)
        stats = RenderStats(views=res.views, selection=sel, hole_frac_per_view=res.hole_frac_per_view, ms=res.ms,
                            skipped=res.skipped, completed=res.completed, reused_selection=reused,
                            lod_levels=[frame.levels.get(v, 0) for v in res.views])
        color = res.color if self._output_vignetting is None else self._output_vignetting(res.color, K)
        return RGBD(color, res.depth_m, res.valid, res.source_view, K, T_world_cam, res.hole_frac), stats

    def _schedule(self, frame: _FrameViews, stream: _Stream) -> None:
        """Tell the executor what this frame will likely need: the later candidates the previous frame
        drew (warped ahead on the helper thread)."""
        ex, later = self.executor, frame.candidates[1:self.executor.max_later]
        if stream.views_drawn and ex.ahead_possible(frame.K):
            drawn = set(stream.views_drawn)
            views = [ex.cache.peek(v if frame.level(v) == 0 else (v, frame.level(v))) for v in later if v in drawn]
            ex.warp_ahead([v for v in views if v is not None], frame.T_cam_world, frame.K, self.config.near_m)

    def _reusable(self, T_world_cam: np.ndarray, K: Intrinsics, stream: _Stream) -> Selection | None:
        """The stream's previous selection when the camera moved little (temporal coherence)."""
        cfg = self.config
        if stream.prev is None or cfg.reuse_move_m <= 0:
            return None
        T_prev, K_prev, sel = stream.prev
        # on Python floats: the numpy calls of the same tests took ~45 µs per frame
        a, b = T_world_cam[:3].tolist(), T_prev[:3].tolist()
        if K_prev != K or math.dist((a[0][3], a[1][3], a[2][3]), (b[0][3], b[1][3], b[2][3])) > cfg.reuse_move_m:
            return None
        cos = (sum(a[i][j] * b[i][j] for i in range(3) for j in range(3)) - 1.0) / 2.0  # trace(R_prev^T R)
        if math.degrees(math.acos(min(max(cos, -1.0), 1.0))) > cfg.reuse_turn_deg:
            return None
        return sel


def _check_K(K) -> Intrinsics:
    """The target intrinsics: an :class:`~presim.geometry.Intrinsics`, or a scene's per-frame list of
    them when they are all equal (``scene.intrinsics``)."""
    if isinstance(K, Intrinsics):
        return K
    if isinstance(K, (list, tuple)) and K and all(isinstance(k, Intrinsics) for k in K) and all(k == K[0] for k in K):
        return K[0]
    raise ValueError(f"K must be presim.geometry.Intrinsics (or a list of equal ones), got {type(K).__name__}")
