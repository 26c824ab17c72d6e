"""Register a depth image from its own camera into the color camera (what raw Kinect / RealSense
streams need before color and depth share pixels).

Each valid depth pixel is back-projected, moved by ``T_color_depth`` and splatted into the color image
over its whole projected footprint (the rectangle spanned by its projected corners, as librealsense's
``align`` does), keeping the nearest depth per color pixel (z-buffer). Splatting the footprint instead
of one point avoids the regular pinholes a magnifying registration leaves (e.g. a 477 px depth focal
length into a 615 px color camera). Depth values are the z-depth *in the color camera*.

Two implementations: :func:`register_depth_reference` (vectorised numpy, obviously correct) and a numba
kernel (default); ``tests/test_capture_register_depth.py`` checks that they agree.
"""

from __future__ import annotations

import numba
import numpy as np

from presim.geometry import Intrinsics, check_rigid, project, unproject

__all__ = ["register_depth", "register_depth_reference"]


def _corners(depth_m: np.ndarray, K_depth: Intrinsics, K_color: Intrinsics, T_color_depth: np.ndarray):
    """Projected footprints: for each valid depth pixel, z in the color camera and the integer pixel
    range [u0, u1] x [v0, v1] whose centres its footprint covers."""
    vs, us = np.nonzero(np.isfinite(depth_m) & (depth_m > 0))
    z = depth_m[vs, us].astype(np.float64)
    R, t = T_color_depth[:3, :3], T_color_depth[:3, 3]
    us_f, vs_f = us.astype(np.float64), vs.astype(np.float64)
    zc_all, uu, vv = [], [], []
    for du, dv in ((-0.5, -0.5), (0.5, 0.5), (0.0, 0.0)):
        p = unproject(K_depth, np.stack([us_f + du, vs_f + dv], axis=1), z) @ R.T + t
        zc = p[:, 2]
        uv = project(K_color, p)[0]
        uu.append(uv[:, 0])
        vv.append(uv[:, 1])
        zc_all.append(zc)
    zc = zc_all[2]  # depth of the pixel centre
    umin, umax = np.minimum(uu[0], uu[1]), np.maximum(uu[0], uu[1])
    vmin, vmax = np.minimum(vv[0], vv[1]), np.maximum(vv[0], vv[1])
    ok = (zc_all[0] > 0) & (zc_all[1] > 0) & (zc > 0) & np.isfinite(umin + umax + vmin + vmax)
    # Pixel centres inside the footprint; a footprint narrower than a pixel still covers the pixel
    # nearest its centre (rint) so nothing is lost when the color camera has the lower resolution.
    u0 = np.ceil(umin[ok]).astype(np.int64)
    u1 = np.floor(umax[ok]).astype(np.int64)
    v0 = np.ceil(vmin[ok]).astype(np.int64)
    v1 = np.floor(vmax[ok]).astype(np.int64)
    uc = np.rint(uu[2][ok]).astype(np.int64)
    vc = np.rint(vv[2][ok]).astype(np.int64)
    u0, u1 = np.minimum(u0, uc), np.maximum(u1, uc)
    v0, v1 = np.minimum(v0, vc), np.maximum(v1, vc)
    return zc[ok].astype(np.float32), u0, u1, v0, v1


def _check(depth_m, K_depth, K_color, T_color_depth):
    depth_m = np.asarray(depth_m)
    if depth_m.shape != (K_depth.height, K_depth.width):
        raise ValueError(f"depth shape {depth_m.shape} != depth intrinsics {K_depth.height}x{K_depth.width}")
    if not np.issubdtype(depth_m.dtype, np.floating):
        raise ValueError(f"depth must be float metres, got {depth_m.dtype}")
    return depth_m.astype(np.float32, copy=False), check_rigid(T_color_depth, "T_color_depth")


def register_depth_reference(depth_m: np.ndarray, K_depth: Intrinsics, K_color: Intrinsics,
                             T_color_depth: np.ndarray) -> np.ndarray:
    """Numpy reference of :func:`register_depth` (same arguments and result)."""
    depth_m, T = _check(depth_m, K_depth, K_color, T_color_depth)
    z, u0, u1, v0, v1 = _corners(depth_m, K_depth, K_color, T)
    W, H = K_color.width, K_color.height
    lin_all, z_all = [], []
    span_u = int((u1 - u0).max()) + 1 if len(z) else 0
    span_v = int((v1 - v0).max()) + 1 if len(z) else 0
    for dv in range(span_v):
        for du in range(span_u):
            u, v = u0 + du, v0 + dv
            m = (u <= u1) & (v <= v1) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            lin_all.append(v[m] * W + u[m])
            z_all.append(z[m])
    out = np.zeros(H * W, np.float32)
    if lin_all:
        lin, zz = np.concatenate(lin_all), np.concatenate(z_all)
        # Nearest surface wins: minimum z per color pixel.
        out[:] = np.inf
        np.minimum.at(out, lin, zz)
        out[~np.isfinite(out)] = 0.0
    return out.reshape(H, W)


@numba.njit(cache=True)
def _splat_min(z, u0, u1, v0, v1, H, W):
    out = np.full((H, W), np.inf, dtype=np.float32)
    for i in range(z.shape[0]):
        for v in range(max(v0[i], 0), min(v1[i], H - 1) + 1):
            for u in range(max(u0[i], 0), min(u1[i], W - 1) + 1):
                if z[i] < out[v, u]:
                    out[v, u] = z[i]
    for v in range(H):
        for u in range(W):
            if out[v, u] == np.inf:
                out[v, u] = 0.0
    return out


def register_depth(depth_m: np.ndarray, K_depth: Intrinsics, K_color: Intrinsics,
                   T_color_depth: np.ndarray) -> np.ndarray:
    """Depth of the depth camera resampled into the color camera.

    Args:
        depth_m: float (Hd, Wd) z-depth of the depth camera, metres, 0 = invalid.
        K_depth: intrinsics of the depth image.
        K_color: intrinsics of the color image (output size).
        T_color_depth: 4x4 depth-camera -> color-camera transform (metres).

    Returns:
        float32 (H, W) z-depth in the color camera, 0 where no depth pixel lands.

    Example:
        >>> K = Intrinsics(500, 500, 319.5, 239.5, 640, 480)
        >>> d = np.full((480, 640), 2.0, np.float32)
        >>> float(register_depth(d, K, K, np.eye(4))[240, 320])
        2.0
    """
    depth_m, T = _check(depth_m, K_depth, K_color, T_color_depth)
    z, u0, u1, v0, v1 = _corners(depth_m, K_depth, K_color, T)
    return _splat_min(z, u0, u1, v0, v1, K_color.height, K_color.width)
