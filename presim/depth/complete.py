"""Depth completion of capture frames: geometry where the sensor has none.

Registered Kinect-style depth misses the image borders (the first rows are mostly empty in every
frame) and dark or shiny surfaces, while the colour image covers them. A pixel a target camera sees
only there becomes a hole that the renderer must inpaint. Completion gives such pixels a depth,
in two steps per frame:

1. **Surface continuation** (:func:`complete_frame`): empty pixels within ``max_dist_px`` of measured
   depth are visited nearest first; each fits the plane ``1/z = a u + b v + c`` (a plane in the camera
   frame has an inverse depth affine in the pixel coordinates) to the measured and already completed
   pixels of its window, weighted by colour similarity (so the fit stays on the pixel's own surface
   across colour edges) and distance; completed pixels weigh less than measured ones. A plane is thus
   continued exactly, and the front propagates into wide border bands.
2. **Multi-view check** (:func:`check_completion`): each completed point is projected into the nearest
   views. A view whose measured depth lies *behind* the point saw through it (free-space violation:
   rejected); a view whose depth lies in front is occluded there (no vote); every other view compares
   zero-mean grey patches around the two pixels (exposure-invariant) and votes for or against. The
   confidence is the fraction of votes for; a point no view sees gets ``unseen_confidence``.

The renderer uses completed depth only for pixels no measured depth covers (a pass after the adaptive
loop, :mod:`presim.synthesis.pipeline`), so measured geometry always wins.

Units: depth in metres (float32, 0 = none); colours uint8 RGB; poses ``T_world_cam`` (OpenCV camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numba as nb
import numpy as np

from presim.capture.scene import Scene
from presim.geometry import Intrinsics, invert
from presim.io_utils import progress, write_npy_atomic

__all__ = ["CompleteConfig", "complete_frame", "complete_frame_ref", "check_completion", "check_completion_ref",
           "completion_neighbours", "complete_scene_depth", "complete_scene", "COMPLETED_FILE"]


@dataclass(frozen=True)
class CompleteConfig:
    """Parameters of depth completion (pixel sizes are for a 640-pixel-wide image and scale with width)."""

    max_dist_px: float = 48.0
    """Complete empty pixels at most this far from measured depth."""
    radius_px: int = 10
    """Half size of the fitting window."""
    step_px: int = 2
    """Sampling step inside the window."""
    sigma_color: float = 14.0
    """Colour similarity scale (RGB levels, per channel)."""
    completed_weight: float = 0.3
    """Weight of already completed pixels relative to measured ones."""
    min_support: int = 12
    """Fewest window samples to fit a plane."""
    slope_ridge: float = 0.01
    """Ridge on the plane's slope (relative to the window's weight): near-constant fits when the support is thin."""
    neighbours: int = 6
    """Views each completed point is checked in."""
    depth_tol: float = 0.05
    """Relative depth tolerance of the visibility test."""
    patch_px: int = 2
    """Half size of the compared grey patches."""
    color_tol: float = 10.0
    """Mean absolute zero-mean grey difference (levels) below which a view votes for a point."""
    unseen_confidence: float = 0.5
    """Confidence of a point no other view sees."""
    min_confidence: float = 0.5
    """Completed pixels below this confidence are dropped."""

    def __post_init__(self) -> None:
        for name in ("max_dist_px", "sigma_color", "depth_tol", "color_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"CompleteConfig.{name} must be finite and > 0, got {v}")
        if self.radius_px < 1 or self.step_px < 1 or self.min_support < 3 or self.neighbours < 0 or self.patch_px < 0:
            raise ValueError("CompleteConfig: radius_px, step_px >= 1, min_support >= 3, neighbours, patch_px >= 0")
        for name in ("completed_weight", "unseen_confidence", "min_confidence"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"CompleteConfig.{name} must be in [0, 1], got {v}")


def _scaled(config: CompleteConfig, width: int) -> tuple[float, int, int]:
    s = width / 640.0
    return (config.max_dist_px * s, max(2, int(round(config.radius_px * s))), max(1, int(round(config.step_px * s))))


def _visit_order(depth_m: np.ndarray, max_dist_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the empty pixels within ``max_dist_px`` of measured depth, nearest first
    (ties in raster order)."""
    empty = ~(depth_m > 0)
    if not empty.any() or empty.all():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    dist = cv2.distanceTransform(empty.astype(np.uint8), cv2.DIST_L2, 3)
    vs, us = np.nonzero(empty & (dist <= max_dist_px))
    order = np.argsort(dist[vs, us], kind="stable")
    return vs[order], us[order]


def _fit_plane(S: np.ndarray, r: np.ndarray, ridge: float) -> float:
    """``c`` of the ridge least squares ``[a, b, c] = argmin`` (normal equations ``S``, right side ``r``)."""
    A = S.copy()
    A[0, 0] += ridge
    A[1, 1] += ridge
    try:
        return float(np.linalg.solve(A, r)[2])
    except np.linalg.LinAlgError:
        return r[2] / S[2, 2]


def complete_frame_ref(depth_m: np.ndarray, color: np.ndarray, config: CompleteConfig = CompleteConfig()) -> np.ndarray:
    """Reference (numpy, slow) of :func:`complete_frame`; tiny images only."""
    depth = np.asarray(depth_m, np.float32)
    H, W = depth.shape
    max_d, rad, step = _scaled(config, W)
    rho = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-12), 0.0)
    state = (depth > 0).astype(np.uint8)
    out = np.zeros((H, W), np.float32)
    col = color.astype(np.float64)
    vs, us = _visit_order(depth, max_d)
    for v, u in zip(vs, us):
        S = np.zeros((3, 3))
        r = np.zeros(3)
        n, wsum, lo, hi = 0, 0.0, np.inf, -np.inf
        for dv in range(-rad, rad + 1, step):
            for du in range(-rad, rad + 1, step):
                y, x = v + dv, u + du
                if not (0 <= y < H and 0 <= x < W) or state[y, x] == 0:
                    continue
                dc = float(np.mean((col[y, x] - col[v, u]) ** 2))
                w = math.exp(-dc / (2 * config.sigma_color ** 2) - (du * du + dv * dv) / (0.5 * rad * rad))
                w *= 1.0 if state[y, x] == 1 else config.completed_weight
                f = np.array([du / rad, dv / rad, 1.0])
                S += w * np.outer(f, f)
                r += w * f * rho[y, x]
                n += 1
                wsum += w
                lo, hi = min(lo, rho[y, x]), max(hi, rho[y, x])
        if n < config.min_support or wsum < 1e-9:
            continue
        c = _fit_plane(S, r, config.slope_ridge * wsum)
        if not (0.5 * lo <= c <= 2.0 * hi) or c <= 0:
            continue
        rho[v, u] = c
        state[v, u] = 2
        out[v, u] = np.float32(1.0 / c)
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _complete_kernel(depth, color, vs, us, rad, step, sigma_c, w_completed, min_support, ridge, out):  # pragma: no cover
    H, W = depth.shape
    rho = np.zeros((H, W), np.float64)
    state = np.zeros((H, W), np.uint8)
    for y in range(H):
        for x in range(W):
            if depth[y, x] > 0:
                rho[y, x] = 1.0 / depth[y, x]
                state[y, x] = 1
    inv2c = 1.0 / (2.0 * sigma_c * sigma_c)
    inv_s = 1.0 / (0.5 * rad * rad)
    S = np.zeros((3, 3))
    A = np.zeros((3, 3))
    r = np.zeros(3)
    for i in range(vs.shape[0]):
        v = vs[i]
        u = us[i]
        S[:] = 0.0
        r[:] = 0.0
        n = 0
        wsum = 0.0
        lo = np.inf
        hi = -np.inf
        for dv in range(-rad, rad + 1, step):
            y = v + dv
            if y < 0 or y >= H:
                continue
            for du in range(-rad, rad + 1, step):
                x = u + du
                if x < 0 or x >= W or state[y, x] == 0:
                    continue
                dc = 0.0
                for k in range(3):
                    e = float(color[y, x, k]) - float(color[v, u, k])
                    dc += e * e
                w = math.exp(-(dc / 3.0) * inv2c - (du * du + dv * dv) * inv_s)
                if state[y, x] == 2:
                    w *= w_completed
                f0 = du / rad
                f1 = dv / rad
                p = rho[y, x]
                S[0, 0] += w * f0 * f0
                S[0, 1] += w * f0 * f1
                S[0, 2] += w * f0
                S[1, 1] += w * f1 * f1
                S[1, 2] += w * f1
                S[2, 2] += w
                r[0] += w * f0 * p
                r[1] += w * f1 * p
                r[2] += w * p
                n += 1
                wsum += w
                lo = min(lo, p)
                hi = max(hi, p)
        if n < min_support or wsum < 1e-9:
            continue
        S[1, 0] = S[0, 1]
        S[2, 0] = S[0, 2]
        S[2, 1] = S[1, 2]
        A[:] = S
        A[0, 0] += ridge * wsum
        A[1, 1] += ridge * wsum
        # Cramer's rule for the constant term c of [a, b, c]
        det = (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
               + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))
        if abs(det) > 1e-12 * wsum * wsum * wsum:
            c = (A[0, 0] * (A[1, 1] * r[2] - r[1] * A[2, 1]) - A[0, 1] * (A[1, 0] * r[2] - r[1] * A[2, 0])
                 + r[0] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])) / det
        else:
            c = r[2] / S[2, 2]
        if c <= 0 or c < 0.5 * lo or c > 2.0 * hi:
            continue
        rho[v, u] = c
        state[v, u] = 2
        out[v, u] = np.float32(1.0 / c)


def complete_frame(depth_m: np.ndarray, color: np.ndarray, config: CompleteConfig = CompleteConfig()) -> np.ndarray:
    """Depth for the empty pixels of one frame by surface continuation (module docstring, step 1).

    Args:
        depth_m: float32 (H, W) measured depth, 0 = none.
        color: uint8 (H, W, 3) the frame's colour.
    Returns:
        float32 (H, W): completed depth on pixels that had none (0 elsewhere and where no fit was possible).
    """
    depth = np.ascontiguousarray(depth_m, np.float32)
    if depth.ndim != 2 or color.shape != depth.shape + (3,) or color.dtype != np.uint8:
        raise ValueError(f"complete_frame: depth (H, W) float32 and colour (H, W, 3) uint8, got {depth.shape} "
                         f"and {color.dtype} {color.shape}")
    depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
    max_d, rad, step = _scaled(config, depth.shape[1])
    vs, us = _visit_order(depth, max_d)
    out = np.zeros(depth.shape, np.float32)
    if len(vs):
        # the reference's ridge is relative to the window's weight sum, as here
        _complete_kernel(depth, np.ascontiguousarray(color), vs, us, rad, step, float(config.sigma_color),
                         float(config.completed_weight), int(config.min_support), float(config.slope_ridge), out)
    return out


def _grey(color: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY).astype(np.float32)


def _cams(Ks: Sequence[Intrinsics]) -> np.ndarray:
    return np.array([[K.fx, K.fy, K.cx, K.cy] for K in Ks], np.float64)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _patch_diff(g0, v0, u0, g1, v1, u1, h):  # pragma: no cover
    # mean |(g0 - mean g0) - (g1 - mean g1)| over the (2h+1)^2 patches
    m0 = 0.0
    m1 = 0.0
    n = (2 * h + 1) * (2 * h + 1)
    for dv in range(-h, h + 1):
        for du in range(-h, h + 1):
            m0 += g0[v0 + dv, u0 + du]
            m1 += g1[v1 + dv, u1 + du]
    m0 /= n
    m1 /= n
    s = 0.0
    for dv in range(-h, h + 1):
        for du in range(-h, h + 1):
            s += abs((g0[v0 + dv, u0 + du] - m0) - (g1[v1 + dv, u1 + du] - m1))
    return s / n


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _check_kernel(comp, grey, cam, T_world_cam, greys, depths, cams, T_cam_world, params, conf):  # pragma: no cover
    # params = (depth_tol, patch_px, color_tol, unseen_confidence)
    tol, h, color_tol, unseen = params[0], int(params[1]), params[2], params[3]
    H, W = comp.shape
    M = greys.shape[0]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for v in range(H):
        for u in range(W):
            z = comp[v, u]
            if z <= 0:
                continue
            xc = (u - cx) / fx * z
            yc = (v - cy) / fy * z
            X = T_world_cam[0, 0] * xc + T_world_cam[0, 1] * yc + T_world_cam[0, 2] * z + T_world_cam[0, 3]
            Y = T_world_cam[1, 0] * xc + T_world_cam[1, 1] * yc + T_world_cam[1, 2] * z + T_world_cam[1, 3]
            Z = T_world_cam[2, 0] * xc + T_world_cam[2, 1] * yc + T_world_cam[2, 2] * z + T_world_cam[2, 3]
            agree = 0
            votes = 0
            violated = False
            inside0 = h <= v < H - h and h <= u < W - h
            for j in range(M):
                T = T_cam_world[j]
                xj = T[0, 0] * X + T[0, 1] * Y + T[0, 2] * Z + T[0, 3]
                yj = T[1, 0] * X + T[1, 1] * Y + T[1, 2] * Z + T[1, 3]
                zj = T[2, 0] * X + T[2, 1] * Y + T[2, 2] * Z + T[2, 3]
                if zj <= 1e-6:
                    continue
                uj = int(math.floor(cams[j, 0] * xj / zj + cams[j, 2] + 0.5))
                vj = int(math.floor(cams[j, 1] * yj / zj + cams[j, 3] + 0.5))
                if uj < h or vj < h or uj >= W - h or vj >= H - h:
                    continue
                dj = depths[j, vj, uj]
                if dj > 0:
                    if dj < zj * (1.0 - tol):
                        continue  # occluded in view j: no vote
                    if dj > zj * (1.0 + tol):
                        violated = True  # view j sees through the point
                        break
                if not inside0:
                    continue
                votes += 1
                if _patch_diff(grey, v, u, greys[j], vj, uj, h) < color_tol:
                    agree += 1
            if violated:
                conf[v, u] = 0.0
            elif votes == 0:
                conf[v, u] = unseen
            else:
                conf[v, u] = agree / votes


def check_completion_ref(comp: np.ndarray, grey: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                         greys: np.ndarray, depths: np.ndarray, Ks: Sequence[Intrinsics], T_world_cams: np.ndarray,
                         config: CompleteConfig = CompleteConfig()) -> np.ndarray:
    """Reference (numpy, per pixel) of :func:`check_completion`."""
    H, W = comp.shape
    h, tol = config.patch_px, config.depth_tol
    conf = np.zeros((H, W), np.float32)
    T_cw = invert(np.asarray(T_world_cams, np.float64))
    for v, u in zip(*np.nonzero(comp > 0)):
        z = float(comp[v, u])
        Xw = T_world_cam @ np.array([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z, 1.0])
        agree = votes = 0
        violated = False
        for j, Kj in enumerate(Ks):
            xj = T_cw[j] @ Xw
            if xj[2] <= 1e-6:
                continue
            uj = int(math.floor(Kj.fx * xj[0] / xj[2] + Kj.cx + 0.5))
            vj = int(math.floor(Kj.fy * xj[1] / xj[2] + Kj.cy + 0.5))
            if not (h <= uj < W - h and h <= vj < H - h):
                continue
            dj = depths[j, vj, uj]
            if dj > 0 and dj < xj[2] * (1 - tol):
                continue
            if dj > 0 and dj > xj[2] * (1 + tol):
                violated = True
                break
            if not (h <= v < H - h and h <= u < W - h):
                continue
            p0 = grey[v - h:v + h + 1, u - h:u + h + 1]
            p1 = greys[j, vj - h:vj + h + 1, uj - h:uj + h + 1]
            votes += 1
            agree += float(np.mean(np.abs((p0 - p0.mean()) - (p1 - p1.mean())))) < config.color_tol
        conf[v, u] = 0.0 if violated else (config.unseen_confidence if votes == 0 else agree / votes)
    return conf


def check_completion(comp: np.ndarray, grey: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                     greys: np.ndarray, depths: np.ndarray, Ks: Sequence[Intrinsics], T_world_cams: np.ndarray,
                     config: CompleteConfig = CompleteConfig()) -> np.ndarray:
    """Confidence in [0, 1] of each completed pixel (module docstring, step 2; 0 where ``comp`` is 0).

    Args:
        comp: float32 (H, W) completed depth of the frame; grey: float32 (H, W) its grey image;
        K, T_world_cam: its intrinsics and pose.
        greys, depths: float32 (M, H, W) the neighbour views' grey images and measured depth;
        Ks, T_world_cams: their intrinsics and (M, 4, 4) poses.
    """
    conf = np.zeros(comp.shape, np.float32)
    if len(Ks) == 0:
        conf[comp > 0] = config.unseen_confidence
        return conf
    T_cw = np.ascontiguousarray(invert(np.asarray(T_world_cams, np.float64)))
    _check_kernel(np.ascontiguousarray(comp, np.float32), np.ascontiguousarray(grey, np.float32),
                  _cams([K])[0], np.ascontiguousarray(T_world_cam, np.float64),
                  np.ascontiguousarray(greys, np.float32), np.ascontiguousarray(depths, np.float32), _cams(Ks),
                  T_cw, np.array([config.depth_tol, config.patch_px, config.color_tol, config.unseen_confidence],
                                 np.float64), conf)
    return conf


def completion_neighbours(T_world_cam: np.ndarray, idx: int, pool: Sequence[int], k: int) -> list[int]:
    """The ``k`` views of ``pool`` (not ``idx``) nearest to view ``idx``: camera distance (m) plus half
    the angle between the optical axes (rad)."""
    cand = [int(j) for j in pool if int(j) != idx]
    if not cand or k == 0:
        return []
    T = np.asarray(T_world_cam)
    d = np.linalg.norm(T[cand, :3, 3] - T[idx, :3, 3], axis=1)
    cosang = np.clip(T[cand, :3, 2] @ T[idx, :3, 2], -1.0, 1.0)
    score = d + 0.5 * np.arccos(cosang)
    return [cand[i] for i in np.argsort(score, kind="stable")[:k]]


def complete_scene_depth(scene: Scene, depth: np.ndarray | None = None, config: CompleteConfig = CompleteConfig(),
                         pool: Sequence[int] | None = None, out: np.ndarray | None = None,
                         desc: str = "complete depth") -> np.ndarray:
    """Completed depth of every frame of ``scene`` (float32 (N, H, W), 0 where not completed or dropped).

    Args:
        depth: (N, H, W) the depth the renderer uses (default: the scene's refined depth, else its raw depth).
        pool: the frames the multi-view check may use (default: all).
        out: array to write into (e.g. a memory-mapped file), else a new one.
    """
    n, H, W = len(scene), scene.height, scene.width
    if depth is None:
        depth = scene.depth_refined
    raw = depth is None

    def dep(i: int) -> np.ndarray:
        d = scene.frames.load(i)[1] if raw else np.asarray(depth[i])
        if d.shape != (H, W):
            raise ValueError(f"frame {scene.frame_ids[i]}: depth shape {d.shape} != {(H, W)}")
        return np.where(np.isfinite(d), d, 0).astype(np.float32)

    pool = list(range(n)) if pool is None else [int(j) for j in pool]
    greys: dict[int, np.ndarray] = {}

    def grey(i: int) -> np.ndarray:
        g = greys.get(i)
        if g is None:
            g = greys[i] = _grey(scene.frames.load(i)[0])
        return g

    if out is None:
        out = np.zeros((n, H, W), np.float32)
    for i in progress(range(n), desc=desc, unit="frame"):
        color = scene.frames.load(i)[0]
        comp = complete_frame(dep(i), color, config)
        nb_ids = completion_neighbours(scene.T_world_cam, i, pool, config.neighbours)
        conf = check_completion(comp, grey(i), scene.intrinsics[i], scene.T_world_cam[i],
                                np.stack([grey(j) for j in nb_ids]) if nb_ids else np.zeros((0, H, W), np.float32),
                                np.stack([dep(j) for j in nb_ids]) if nb_ids else np.zeros((0, H, W), np.float32),
                                [scene.intrinsics[j] for j in nb_ids], scene.T_world_cam[nb_ids], config)
        out[i] = np.where(conf >= config.min_confidence, comp, 0).astype(np.float32)
    return out


COMPLETED_FILE = "depth_completed.npy"


def complete_scene(scene: Scene, overwrite: bool = False, config: CompleteConfig = CompleteConfig()) -> Path:
    """``presim complete``: :func:`complete_scene_depth` of a saved scene (on its refined depth when it has
    one, else its raw depth) into ``SCENE/depth_completed.npy`` (atomic: ``.partial`` then rename)."""
    if scene.path is None:
        raise ValueError("complete_scene needs a saved scene (load it with presim.capture.store.load_scene)")
    dst = Path(scene.path) / COMPLETED_FILE
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: already exists (pass --overwrite to recompute)")
    return write_npy_atomic(dst, np.float32, (len(scene), scene.height, scene.width),
                            lambda arr: complete_scene_depth(scene, config=config, out=arr))
