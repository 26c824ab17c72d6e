"""Tiny analytic scenes for tests and benchmarks: textured rectangles ray cast exactly.

A scene is a list of :class:`Rect` (planar textured rectangles in the world). :func:`raycast` renders
exact color + z-depth at any pose; :func:`make_scene` renders a set of poses into an in-memory
:class:`~presim.capture.scene.Scene` (ArrayFrameSource), so synthesized views can be compared with
exact ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
from presim.geometry import Intrinsics, look_at

__all__ = ["Rect", "raycast", "make_scene", "plane_rects", "room_rects", "orbit_poses"]


@dataclass(frozen=True)
class Rect:
    """Rectangle ``origin + a*edge_u + b*edge_v`` for a, b in [0, 1], with a procedural texture."""

    origin: tuple[float, float, float]
    edge_u: tuple[float, float, float]
    edge_v: tuple[float, float, float]
    base_rgb: tuple[int, int, int] = (180, 120, 60)
    checker_m: float = 0.1
    """Checker square size, metres (0 = flat color)."""


def raycast(rects: list[Rect], T_world_cam: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Exact color uint8 (H, W, 3) and z-depth float32 (H, W) (0 = no hit) of the rectangles."""
    H, W = K.height, K.width
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1)  # z = 1 rays
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d_w = d_cam @ R.T
    best_t = np.full((H, W), np.inf)
    color = np.zeros((H, W, 3), np.uint8)
    for r in rects:
        p0, eu, ev = (np.asarray(x, np.float64) for x in (r.origin, r.edge_u, r.edge_v))
        n = np.cross(eu, ev)
        denom = d_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p0 - o) @ n) / denom
        hit = o + d_w * t[..., None] - p0
        a = hit @ eu / (eu @ eu)
        b = hit @ ev / (ev @ ev)
        ok = (t > 1e-6) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (t < best_t)
        best_t[ok] = t[ok]
        base = np.asarray(r.base_rgb, np.float64)
        if r.checker_m > 0:
            su, sv = a * np.linalg.norm(eu) / r.checker_m, b * np.linalg.norm(ev) / r.checker_m
            chk = ((np.floor(su) + np.floor(sv)) % 2)[..., None]
            shade = 0.6 + 0.4 * chk + 0.15 * np.sin(7.0 * su[..., None] + 3.0 * sv[..., None] + np.arange(3))
        else:
            shade = np.ones((H, W, 1))
        col = np.clip(base * shade, 0, 255).astype(np.uint8)
        color[ok] = col[ok]
    depth = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32)  # z-depth (rays have z = 1)
    return color, depth


def make_scene(rects: list[Rect], T_world_cams: np.ndarray, K: Intrinsics, name: str = "synthetic") -> Scene:
    """In-memory Scene of the rectangles seen from each pose (exact depth, no noise)."""
    T = np.asarray(T_world_cams, np.float64)
    cols, deps = zip(*(raycast(rects, t, K) for t in T))
    return Scene(
        frame_ids=[f"frame-{i:06d}" for i in range(len(T))], stamps_s=np.arange(len(T)) * 0.1,
        T_world_cam=T, intrinsics=[K] * len(T),
        frames=ArrayFrameSource(np.stack(cols), np.stack(deps)),
        meta=SceneMeta(source=name, source_format="synthetic"),
    )


def plane_rects(z_m: float = 2.0, half_m: float = 10.0, checker_m: float = 0.1) -> list[Rect]:
    """One large fronto-parallel plane at world z = ``z_m`` facing an identity camera."""
    return [Rect((-half_m, -half_m, z_m), (2 * half_m, 0, 0), (0, 2 * half_m, 0), checker_m=checker_m)]


def room_rects() -> list[Rect]:
    """A 4 x 3 x 2.5 m textured room (floor z = 0) with a table-sized box in it."""
    rs = [
        Rect((-2, -1.5, 0), (4, 0, 0), (0, 3, 0), (150, 140, 120), 0.25),      # floor
        Rect((-2, 1.5, 0), (4, 0, 0), (0, 0, 2.5), (90, 140, 200), 0.3),       # back wall
        Rect((-2, -1.5, 0), (0, 3, 0), (0, 0, 2.5), (200, 180, 90), 0.3),      # left wall
        Rect((2, -1.5, 0), (0, 3, 0), (0, 0, 2.5), (120, 200, 120), 0.3),      # right wall
    ]
    # Box 0.6 x 0.6 x 0.7 m at the centre.
    x0, y0, z0, s, h = -0.3, 0.2, 0.0, 0.6, 0.7
    rs += [
        Rect((x0, y0, z0), (s, 0, 0), (0, 0, h), (200, 60, 60), 0.1),
        Rect((x0, y0 + s, z0), (s, 0, 0), (0, 0, h), (200, 60, 60), 0.1),
        Rect((x0, y0, z0), (0, s, 0), (0, 0, h), (60, 60, 200), 0.1),
        Rect((x0 + s, y0, z0), (0, s, 0), (0, 0, h), (60, 60, 200), 0.1),
        Rect((x0, y0, z0 + h), (s, 0, 0), (0, s, 0), (230, 230, 80), 0.08),
    ]
    return rs


def orbit_poses(n: int, span_m: float = 1.2, y_m: float = -1.0, height_m: float = 1.3,
                target=(0.0, 0.5, 0.4)) -> np.ndarray:
    """``n`` look-at poses on a line (x in [-span/2, span/2]) in front of the room's box, (n, 4, 4)."""
    xs = np.linspace(-span_m / 2, span_m / 2, n)
    return np.stack([look_at((x, y_m, height_m), target) for x in xs])
