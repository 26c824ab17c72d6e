"""A tiny RGB-D capture with answers known on paper, for the pose-alignment tests.

Two textured fronto-parallel planes (z = 2.0 m for x < 0.1, z = 2.4 m beyond), seen by cameras near
the origin looking along +z. Color is a smooth multi-scale random texture (SIFT finds blobs), depth
is exact, poses are exact: any error after alignment is the algorithm's.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
from presim.geometry import Intrinsics, make_pose

PLANES = ((2.0, -10.0, 0.1), (2.4, 0.1, 10.0))  # (z, x_min, x_max)
TEX_M = 4.0  # texture covers x, y in [-2, 2] m


def texture(seed: int = 0, size: int = 1024) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size, 3), np.float32)
    for s in (4, 8, 16, 32, 64):
        small = rng.random((size // s, size // s, 3)).astype(np.float32)
        tex += cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC) / 5
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return (tex * 255).astype(np.uint8)


def render(T_world_cam: np.ndarray, K: Intrinsics, tex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(color uint8 (H, W, 3), depth float32 (H, W)) of the two planes."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1)
    R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d_w = d_cam @ R.T
    best_t = np.full(u.shape, np.inf)
    hit = np.zeros(u.shape + (3,))
    for z, x0, x1 in PLANES:
        t = (z - c[2]) / d_w[..., 2]
        p = c + t[..., None] * d_w
        ok = (t > 0) & (p[..., 0] >= x0) & (p[..., 0] < x1) & (t < best_t)
        best_t[ok] = t[ok]
        hit[ok] = p[ok]
    n = tex.shape[0]
    mx = ((hit[..., 0] + TEX_M / 2) / TEX_M * n - 0.5).astype(np.float32)
    my = ((hit[..., 1] + TEX_M / 2) / TEX_M * n - 0.5).astype(np.float32)
    color = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    p_cam = (hit - c) @ R  # world -> camera
    depth = np.where(np.isfinite(best_t), p_cam[..., 2], 0).astype(np.float32)
    return color, depth


def trajectory(n: int = 8, step_m: float = 0.04, seed: int = 0) -> np.ndarray:
    """Cameras on a short arc near the origin, looking along +z with a few degrees of yaw/pitch."""
    poses = []
    for i in range(n):
        R = Rotation.from_euler("yxz", [np.radians(2.0 * i - 7), np.radians(1.5 * np.sin(i)), 0]).as_matrix()
        poses.append(make_pose(R, [step_m * i - 0.15, 0.02 * np.cos(i), 0.05 * np.sin(0.5 * i)]))
    return np.stack(poses)


def perturb(T: np.ndarray, trans_m: float, rot_deg: float, seed: int) -> np.ndarray:
    """Each pose moved by exactly ``trans_m`` and rotated by exactly ``rot_deg`` in random directions."""
    rng = np.random.default_rng(seed)
    out = T.copy()
    for i in range(len(T)):
        a = rng.normal(size=3)
        b = rng.normal(size=3)
        out[i, :3, :3] = Rotation.from_rotvec(a / np.linalg.norm(a) * np.radians(rot_deg)).as_matrix() @ T[i, :3, :3]
        out[i, :3, 3] += b / np.linalg.norm(b) * trans_m
    return out


def synthetic_scene(n: int = 8, width: int = 320, height: int = 240, seed: int = 0,
                    T_world_cam: np.ndarray | None = None) -> tuple[Scene, np.ndarray]:
    """(scene with poses ``T_world_cam`` (default: exact), exact poses)."""
    K = Intrinsics(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    T = trajectory(n)
    tex = texture(seed)
    frames = [render(T[i], K, tex) for i in range(n)]
    color = np.stack([f[0] for f in frames])
    depth = np.stack([f[1] for f in frames])
    poses = T if T_world_cam is None else T_world_cam
    scene = Scene([f"frame-{i:06d}" for i in range(n)], np.arange(n) / 30.0, poses, [K] * n,
                  ArrayFrameSource(color, depth), SceneMeta("synthetic", "test"))
    return scene, T
