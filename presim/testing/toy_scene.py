"""A tiny analytic scene for tests and benchmarks: a box room with a pillar, ray cast exactly.

Room ``[0, size_x] x [0, size_y] x [0, height]`` (floor z = 0, gravity -z), walls at its sides, an
axis-aligned pillar, a procedural checker texture keyed to world coordinates (so every view of a
surface agrees). Captured views stand on a ring around the room centre at ``cam_height_m`` looking
outwards. Everything is exact, so the simulator's collision and kinematics have known answers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.capture.scene import ArrayFrameSource, FloorPlane, Scene, SceneMeta
from presim.geometry import Intrinsics, look_at, pixel_grid

__all__ = ["ToyRoomConfig", "build_toy_room", "raycast_toy_room"]


@dataclass(frozen=True)
class ToyRoomConfig:
    """Box room geometry and capture."""

    size_x_m: float = 5.0
    """Room length along x, metres."""
    size_y_m: float = 4.0
    """Room width along y, metres."""
    height_m: float = 2.5
    """Ceiling height, metres."""
    pillar_min: tuple[float, float, float] = (3.4, 1.6, 0.0)
    """Pillar box lower corner (x, y, z), metres."""
    pillar_max: tuple[float, float, float] = (3.8, 2.4, 1.5)
    """Pillar box upper corner, metres."""
    num_views: int = 12
    """Captured views on a ring around the room centre."""
    ring_radius_m: float = 0.6
    """Ring radius, metres."""
    cam_height_m: float = 1.1
    """Camera height, metres."""
    width: int = 160
    """Captured image width, pixels."""
    height: int = 120
    """Captured image height, pixels."""
    hfov_deg: float = 70.0
    """Captured horizontal field of view."""


def raycast_toy_room(T_world_cam: np.ndarray, K: Intrinsics, cfg: ToyRoomConfig = ToyRoomConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Exact (color uint8 (H, W, 3), depth_m float32 (H, W)) of the toy room from ``T_world_cam``."""
    uv = pixel_grid(K.width, K.height).reshape(-1, 2)
    d_cam = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = d_cam @ R.T  # ray directions (z-depth = t since d_cam has z = 1)
    t_best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Room: the ray leaves the box through the nearest face ahead (inside the room).
        lo = np.array([0.0, 0.0, 0.0])
        hi = np.array([cfg.size_x_m, cfg.size_y_m, cfg.height_m])
        for ax in range(3):
            for bound in (lo[ax], hi[ax]):
                t = (bound - o[ax]) / d[:, ax]
                t_best = np.where((t > 1e-6) & (t < t_best), t, t_best)
        # Pillar (slab method), nearest entry.
        pmin, pmax = np.array(cfg.pillar_min), np.array(cfg.pillar_max)
        t1 = (pmin - o) / d
        t2 = (pmax - o) / d
        tn = np.nanmax(np.minimum(t1, t2), axis=1)
        tf = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tn <= tf) & (tn > 1e-6)
        t_best = np.where(hit & (tn < t_best), tn, t_best)
    p = o + d * t_best[:, None]
    # Checker texture (25 cm squares) with a per-axis tint so walls differ.
    q = np.floor(p / 0.25).astype(np.int64)
    checker = ((q[:, 0] + q[:, 1] + q[:, 2]) & 1).astype(np.float64)
    base = np.stack([0.5 + 0.4 * np.sin(p[:, 0] * 1.3), 0.5 + 0.4 * np.sin(p[:, 1] * 1.7 + 1.0),
                     0.5 + 0.4 * np.sin(p[:, 2] * 2.1 + 2.0)], axis=1)
    color = np.clip(255 * base * (0.6 + 0.4 * checker[:, None]), 0, 255).astype(np.uint8)
    depth = np.where(np.isfinite(t_best), t_best, 0.0).astype(np.float32)
    return color.reshape(K.height, K.width, 3), depth.reshape(K.height, K.width)


def build_toy_room(cfg: ToyRoomConfig = ToyRoomConfig()) -> Scene:
    """In-memory :class:`Scene` of the toy room (floor set at z = 0; no point cloud: the simulator
    fuses one)."""
    K = Intrinsics.from_fov(cfg.width, cfg.height, cfg.hfov_deg)
    c = np.array([cfg.size_x_m / 2, cfg.size_y_m / 2, cfg.cam_height_m])
    poses, colors, depths = [], [], []
    for k in range(cfg.num_views):
        a = 2 * np.pi * k / cfg.num_views
        eye = c + cfg.ring_radius_m * np.array([np.cos(a), np.sin(a), 0.0])
        target = eye + np.array([np.cos(a), np.sin(a), -0.35])
        T = look_at(eye, target)
        col, dep = raycast_toy_room(T, K, cfg)
        poses.append(T)
        colors.append(col)
        depths.append(dep)
    n = cfg.num_views
    return Scene(
        frame_ids=[f"frame-{k:06d}" for k in range(n)],
        stamps_s=np.arange(n, dtype=np.float64) * 0.1,
        T_world_cam=np.stack(poses),
        intrinsics=[K] * n,
        frames=ArrayFrameSource(np.stack(colors), np.stack(depths)),
        meta=SceneMeta(source="toy-room", source_format="toy"),
        floor=FloorPlane((0.0, 0.0, 1.0), 0.0, 1.0),
    )
