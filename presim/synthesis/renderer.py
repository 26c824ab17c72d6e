"""Renderer: the thin stateful component of the view synthesis engine.

PROVISIONAL: a naive z-buffer splat of the nearest views + inpainting, so that the simulator,
recorder and dataset generator can be built against the final interface. The thesis pipeline
(refinement, adaptive views, layered warping) replaces the internals; the interface stays:

    Renderer(scene, RenderConfig()).render(T_world_cam, K) -> RGBD
    Renderer(...).render_batch(T_world_cams (B,4,4), K) -> list[RGBD]
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from presim.capture.scene import Scene
from presim.geometry import Intrinsics, invert, unproject_depth
from presim.synthesis.rgbd import RGBD

__all__ = ["RenderConfig", "Renderer"]


@dataclass(frozen=True)
class RenderConfig:
    max_views: int = 3
    """Number of nearest captured views splatted."""
    fill_holes: bool = True
    """Fill pixels no view covers (they stay False in ``RGBD.valid``)."""
    use_refined_depth: bool = True
    """Use ``presim refine`` output when the scene has it."""


class Renderer:
    def __init__(self, scene: Scene, config: RenderConfig = RenderConfig()):
        self.scene = scene
        self.config = config
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _points(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        if idx not in self._cache:
            f = self.scene.frame(idx, refined=self.config.use_refined_depth)
            pts, mask = unproject_depth(f.K, f.depth_m, f.T_world_cam)
            self._cache[idx] = (pts, f.color[mask])
        return self._cache[idx]

    def render(self, T_world_cam: np.ndarray, K: Intrinsics) -> RGBD:
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        d = np.linalg.norm(self.scene.camera_centres - T_world_cam[:3, 3], axis=1)
        views = np.argsort(d)[: self.config.max_views]
        H, W = K.height, K.width
        zbuf = np.full(H * W, np.inf, np.float32)
        color = np.zeros((H * W, 3), np.uint8)
        src = np.full(H * W, -1, np.int32)
        T_cam_world = invert(T_world_cam)
        for v in views:
            pts, rgb = self._points(int(v))
            p = pts @ T_cam_world[:3, :3].T.astype(np.float32) + T_cam_world[:3, 3].astype(np.float32)
            z = p[:, 2]
            ok = z > 1e-3
            u = np.round(K.fx * p[ok, 0] / z[ok] + K.cx).astype(np.int64)
            w = np.round(K.fy * p[ok, 1] / z[ok] + K.cy).astype(np.int64)
            zz, cc = z[ok], rgb[ok]
            inb = (u >= 0) & (u < W) & (w >= 0) & (w < H)
            lin, zz, cc = w[inb] * W + u[inb], zz[inb], cc[inb]
            order = np.lexsort((zz, lin))
            lin, zz, cc = lin[order], zz[order], cc[order]
            first = np.ones(len(lin), bool)
            first[1:] = lin[1:] != lin[:-1]
            lin, zz, cc = lin[first], zz[first], cc[first]
            closer = zz < zbuf[lin]
            zbuf[lin[closer]] = zz[closer]
            color[lin[closer]] = cc[closer]
            src[lin[closer]] = v
        valid = np.isfinite(zbuf).reshape(H, W)
        depth = np.where(valid.ravel(), zbuf, 0).astype(np.float32).reshape(H, W)
        color = color.reshape(H, W, 3)
        hole = float(1.0 - valid.mean())
        if self.config.fill_holes and hole > 0:
            holes = (~valid).astype(np.uint8)
            color = cv2.inpaint(color, holes, 3, cv2.INPAINT_TELEA)
            depth = cv2.inpaint(depth, holes, 3, cv2.INPAINT_NS)
        return RGBD(color, depth, valid, src.reshape(H, W), K, T_world_cam, hole)

    def render_batch(self, T_world_cams: np.ndarray, K: Intrinsics) -> list[RGBD]:
        return [self.render(T, K) for T in np.asarray(T_world_cams)]
