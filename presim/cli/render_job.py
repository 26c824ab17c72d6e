"""``presim render``: a scene rendered at camera poses into a capture folder (:mod:`presim.formats.kinfu_folder`
plus ``frame-XXXXXX.valid.png`` and ``render.json``, written last), and the poses the capture covers badly."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.capture.scene import Scene
from presim.formats.kinfu_folder import KinfuFolderWriter
from presim.geometry import Intrinsics
from presim.io_utils import atomic_write_json, progress
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

__all__ = ["output_intrinsics", "render_to_folder", "FarPose", "far_poses"]


def output_intrinsics(K: Intrinsics, width: int | None = None, height: int | None = None, fx: float | None = None,
                      fy: float | None = None, cx: float | None = None, cy: float | None = None) -> Intrinsics:
    """The scene's ``K`` resampled to ``width`` x ``height`` (one given keeps the aspect ratio), then
    ``fx``/``fy``/``cx``/``cy`` replaced where given (pixels).

    Example:
        >>> output_intrinsics(Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480), width=320).size_wh
        (320, 240)
    """
    if width or height:
        w = width or round(K.width * height / K.height)
        h = height or round(K.height * width / K.width)
        K = K.scaled(w, h)
    return Intrinsics(fx or K.fx, fy or K.fy, K.cx if cx is None else cx, K.cy if cy is None else cy,
                      K.width, K.height)


def render_to_folder(scene: Scene, T_world_cams: np.ndarray, stamps_s: np.ndarray, K: Intrinsics, out: Path,
                     config: RenderConfig, batch_size: int = 16, perf: PerfConfig = PerfConfig()) -> dict:
    """Render poses ``T_world_cams`` (B, 4, 4) with ``K`` into folder ``out``, ``batch_size`` per
    :meth:`Renderer.render_batch`; depth PNGs are uint16 mm (values that do not fit: 0, counted). Returns the
    ``render.json`` summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    r = Renderer(scene, config, perf)
    writer = KinfuFolderWriter(out)
    if batch_size < 1:
        raise ValueError(f"batch size must be >= 1, got {batch_size}")
    holes, views, ms = [], [], []
    step = batch_size
    bar = progress(total=len(T_world_cams), desc="render", unit="frame")
    for i0 in range(0, len(T_world_cams), step):
        T = np.asarray(T_world_cams[i0:i0 + step], np.float64)
        t0 = time.perf_counter()
        frames = r.render_batch(T, K)
        used = r.last.batch_views
        ms.extend([(time.perf_counter() - t0) * 1e3 / len(frames)] * len(frames))
        for j, rgbd in enumerate(frames):
            writer.write_frame(rgbd.color, rgbd.depth_m, T[j], K, float(stamps_s[i0 + j]),
                               extra_images={"valid": rgbd.valid})
            holes.append(rgbd.hole_frac_before_fill)
            views.append(len(used[j]))
        bar.update(len(frames))
    bar.close()
    writer.close()
    summary = {
        "scene": str(scene.path) if scene.path else None, "num_frames": len(T_world_cams),
        "intrinsics": K.to_dict(), "config": dataclasses.asdict(config), "perf": dataclasses.asdict(perf),
        "hole_frac_before_fill": holes, "views_used": views,
        "depth_clipped_px": writer.depth_clipped_px,
        "ms_per_frame_median": float(np.median(ms)),
    }
    atomic_write_json(out / "render.json", summary)
    return summary


@dataclass(frozen=True)
class FarPose:
    """A rendered frame whose pose the capture covers badly."""

    frame: int
    distance_m: float
    """Distance to the nearest captured camera centre."""
    nearest_view: int
    hole_frac: float
    """Fraction of the image no captured view covered (before hole filling)."""

    def __str__(self) -> str:
        return (f"frame {self.frame}: pose is {self.distance_m:.2f} m from the nearest captured view "
                f"(frame {self.nearest_view}); {self.hole_frac:.0%} of the image had no captured pixel "
                "before hole filling")


def far_poses(scene, T_world_cams: np.ndarray, hole_fracs, far_m: float = 1.0,
              max_hole_frac: float = 0.5) -> list[FarPose]:
    """Frames more than ``far_m`` from every captured view or with hole fraction above ``max_hole_frac``."""
    centres = np.asarray(scene.camera_centres, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(T_world_cams, dtype=np.float64).reshape(-1, 4, 4)
    out = []
    for i, (Ti, hole) in enumerate(zip(T, hole_fracs)):
        d = np.linalg.norm(centres - Ti[:3, 3], axis=1) if len(centres) else np.array([np.inf])
        k = int(np.argmin(d))
        if d[k] > far_m or float(hole) > max_hole_frac:
            out.append(FarPose(i, float(d[k]), k, float(hole)))
    return out
