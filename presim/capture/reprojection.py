"""Reprojection check: does a capture's depth + poses explain its images?

Forward-warp one frame (the *source*) into another (the *target*) with the source's depth and both
poses, keep the nearest surface per target pixel (z-buffer), and compare colors. With correct
camera-to-world poses and registered metric depth the error is small; a wrong pose convention
(world-to-camera), a wrong depth scale or unregistered depth gives an error as large as, or larger
than, the no-motion baseline (``use_poses=False``: the source image compared pixel by pixel).

Example:
    >>> from presim.capture.store import load_scene
    >>> scene = load_scene("out/kinfu")                            # doctest: +SKIP
    >>> reprojection_mae(scene, 8, 7)                             # doctest: +SKIP
    (6.8, 0.35)
"""

from __future__ import annotations

import numpy as np

from presim.geometry import Intrinsics, compose, invert, project, unproject_depth

__all__ = ["reprojection_mae", "forward_warp", "nearest_pixel", "zbuffer_splat"]


def nearest_pixel(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel each projection ``uv`` (n, 2) lands on, by the conventions' pixel-centre rule.

    Pixel (0, 0) is the centre of the top-left pixel (docs/conventions.md), so pixel ``i`` covers
    ``[i - 0.5, i + 0.5)`` and a projection lands on ``floor(u + 0.5)`` (halves round up, never to
    even). Returns ``(ui, vi, inside)``: int64 (n,) pixel columns/rows and a bool (n,) mask of the
    finite projections inside the ``width`` x ``height`` image (``ui`` / ``vi`` are only meaningful
    where ``inside``).
    """
    uv = np.asarray(uv)
    with np.errstate(invalid="ignore"):
        uf = np.floor(uv[:, 0] + 0.5)
        vf = np.floor(uv[:, 1] + 0.5)
        inside = (uf >= 0) & (uf < width) & (vf >= 0) & (vf < height)  # False for nan
    ui = np.where(inside, uf, 0).astype(np.int64)
    vi = np.where(inside, vf, 0).astype(np.int64)
    return ui, vi, inside


def zbuffer_splat(uv: np.ndarray, z: np.ndarray, width: int, height: int, near_m: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One-pixel z-buffer splat: the front-most point per pixel (the project's one splat rule).

    Each point in front of the camera (``z > near_m``) with a finite projection lands on its
    :func:`nearest_pixel`; each pixel keeps the point of smallest ``z`` (compared in ``z``'s own
    dtype), and on an exact tie the point that comes first (lowest index). Used by
    :func:`forward_warp` and by the synthesis reference kernels (every fast path is tested
    against those).

    Args:
        uv: (n, 2) projections, pixels; z: (n,) camera z-depth (any float dtype), metres.
        width, height: image size.
    Returns:
        ``(pixel, point)``: int64 (k,) flat pixel indices ``v * width + u`` (ascending, unique) and
        int64 (k,) the index of the point that wins each of them.
    """
    z = np.asarray(z)
    with np.errstate(invalid="ignore"):
        front = z > near_m
    ui, vi, inside = nearest_pixel(uv, width, height)
    idx = np.flatnonzero(front & inside)
    lin = vi[idx] * width + ui[idx]
    # Sort by (pixel, depth); lexsort is stable, so equal depths keep the point order.
    order = np.lexsort((z[idx], lin))
    lin, idx = lin[order], idx[order]
    first = np.ones(len(lin), dtype=bool)
    first[1:] = lin[1:] != lin[:-1]
    return lin[first], idx[first]


def forward_warp(color_src: np.ndarray, depth_src_m: np.ndarray, K_src: Intrinsics, K_dst: Intrinsics,
                 T_dst_src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Warp a source RGB-D image into a destination camera with a z-buffer (nearest pixel splat).

    Args:
        color_src: uint8 (H, W, 3).
        depth_src_m: float32 (H, W) z-depth, 0 = invalid.
        K_src, K_dst: intrinsics of source and destination.
        T_dst_src: 4x4 source-camera -> destination-camera.

    Returns:
        ``(color_dst, depth_dst_m)``: uint8 (H', W', 3) and float32 (H', W') with 0 where nothing
        landed; the front-most source point wins each destination pixel (:func:`zbuffer_splat`:
        nearest pixel ``floor(u + 0.5)``, smallest z, ties to the first point).
    """
    color_src = np.asarray(color_src)
    if color_src.shape != (K_src.height, K_src.width, 3):
        raise ValueError(f"color shape {color_src.shape} != intrinsics {K_src.height}x{K_src.width}x3")
    pts, mask = unproject_depth(K_src, depth_src_m, T_dst_src)
    rgb = color_src[mask]
    uv, z = project(K_dst, pts)
    lin, win = zbuffer_splat(uv, z, K_dst.width, K_dst.height, near_m=0.0)
    color_dst = np.zeros((K_dst.height * K_dst.width, 3), np.uint8)
    depth_dst = np.zeros(K_dst.height * K_dst.width, np.float32)
    color_dst[lin] = rgb[win]
    depth_dst[lin] = z[win]
    return color_dst.reshape(K_dst.height, K_dst.width, 3), depth_dst.reshape(K_dst.height, K_dst.width)


def reprojection_mae(scene, target_idx: int, source_idx: int, use_poses: bool = True) -> tuple[float, float]:
    """Mean absolute color error (0-255 levels, averaged over the 3 channels) of the source frame
    forward-warped into the target frame, over the target pixels it covers.

    Args:
        scene: a :class:`presim.capture.scene.Scene`.
        target_idx, source_idx: frame positions.
        use_poses: ``False`` = no-motion baseline (``T_target_source = I``).

    Returns:
        ``(mae_gray_levels, coverage)``: the error and the fraction of target pixels covered
        (``(nan, 0.0)`` when nothing lands in the target).
    """
    n = len(scene)
    for name, idx in (("target_idx", target_idx), ("source_idx", source_idx)):
        if not 0 <= int(idx) < n:
            raise ValueError(f"{name}={idx} out of range for a scene of {n} frames")
    tgt = scene.frame(int(target_idx))
    src = scene.frame(int(source_idx))
    if use_poses:
        T_tgt_src = compose(invert(tgt.T_world_cam), src.T_world_cam)
    else:
        T_tgt_src = np.eye(4)
    warped, depth = forward_warp(src.color, src.depth_m, src.K, tgt.K, T_tgt_src)
    cov = depth > 0
    if not cov.any():
        return float("nan"), 0.0
    err = np.abs(warped[cov].astype(np.float32) - tgt.color[cov].astype(np.float32))
    return float(err.mean()), float(cov.mean())
