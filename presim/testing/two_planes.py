"""Tiny analytic RGB-D scenes with known answers, for tests of refinement and evaluation.

A textured background plane at ``z = bg_z_m`` and a textured foreground square at ``z = fg_z_m``
(world frame = camera frame of the first view, cameras look along +z). Colors are smooth procedural
textures of the world position, so every view is exactly consistent (no exposure changes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.geometry import Intrinsics, make_pose

__all__ = ["TwoPlaneScene", "render_two_planes", "two_plane_poses"]


@dataclass(frozen=True)
class TwoPlaneScene:
    """Geometry and texture of the analytic scene (metres)."""

    bg_z_m: float = 2.0
    """Depth of the background plane."""
    fg_z_m: float = 1.4
    """Depth of the foreground square."""
    fg_half_m: float = 0.25
    """Half side of the foreground square (centred on the z axis)."""
    fg_offset_m: tuple[float, float] = (0.1, 0.0)
    """(x, y) centre of the foreground square."""


def _texture(x: np.ndarray, y: np.ndarray, base: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros(x.shape + (3,))
    for _ in range(6):
        f = rng.uniform(8.0, 30.0, size=2)
        ph = rng.uniform(0, 2 * np.pi)
        amp = rng.uniform(0.03, 0.09, size=3)
        out += amp * np.sin(f[0] * x + f[1] * y + ph)[..., None]
    return np.clip(base + out, 0, 1)


def render_two_planes(T_world_cam: np.ndarray, K: Intrinsics,
                      scene: TwoPlaneScene = TwoPlaneScene()) -> tuple[np.ndarray, np.ndarray]:
    """Exact color uint8 (H,W,3) and z-depth float32 (H,W) of the two-plane scene from a camera."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)
    d_w = d_cam @ T[:3, :3].T
    o = T[:3, 3]
    depth = np.zeros(u.shape)
    color = np.zeros(u.shape + (3,))
    for z_plane, is_fg in ((scene.bg_z_m, False), (scene.fg_z_m, True)):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z_plane - o[2]) / d_w[..., 2]  # d_cam has z = 1, so t is the camera z-depth
        p = o + t[..., None] * d_w
        hit = np.isfinite(t) & (t > 0)
        if is_fg:
            cx, cy = scene.fg_offset_m
            hit &= (np.abs(p[..., 0] - cx) <= scene.fg_half_m) & (np.abs(p[..., 1] - cy) <= scene.fg_half_m)
            base, seed = np.array([0.75, 0.35, 0.25]), 2
        else:
            base, seed = np.array([0.3, 0.45, 0.7]), 1
        closer = hit & ((depth == 0) | (t < depth))
        tex = _texture(p[..., 0], p[..., 1], base, seed)
        depth[closer] = t[closer]
        color[closer] = tex[closer]
    return (np.round(color * 255).astype(np.uint8), depth.astype(np.float32))


def two_plane_poses(n: int, baseline_m: float = 0.05) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses on a small circle in the z = 0 plane, looking along +z."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / max(n, 1)
        t = np.array([baseline_m * np.cos(a), baseline_m * np.sin(a), 0.0]) if i > 0 else np.zeros(3)
        poses.append(make_pose(np.eye(3), t))
    return np.stack(poses)
