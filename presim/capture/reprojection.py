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

__all__ = ["reprojection_mae", "forward_warp"]


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
        landed; the front-most source point wins each destination pixel.
    """
    color_src = np.asarray(color_src)
    if color_src.shape != (K_src.height, K_src.width, 3):
        raise ValueError(f"color shape {color_src.shape} != intrinsics {K_src.height}x{K_src.width}x3")
    pts, mask = unproject_depth(K_src, depth_src_m, T_dst_src)
    rgb = color_src[mask]
    uv, z = project(K_dst, pts)
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    u = np.rint(uv[ok, 0]).astype(np.int64)
    v = np.rint(uv[ok, 1]).astype(np.int64)
    z, rgb = z[ok], rgb[ok]
    inside = (u >= 0) & (u < K_dst.width) & (v >= 0) & (v < K_dst.height)
    u, v, z, rgb = u[inside], v[inside], z[inside], rgb[inside]
    lin = v * K_dst.width + u
    # Z-buffer without relying on write order of duplicate indices: sort by (pixel, depth) and keep
    # the first (nearest) entry of each pixel.
    order = np.lexsort((z, lin))
    lin, z, rgb = lin[order], z[order], rgb[order]
    first = np.ones(len(lin), dtype=bool)
    first[1:] = lin[1:] != lin[:-1]
    color_dst = np.zeros((K_dst.height * K_dst.width, 3), np.uint8)
    depth_dst = np.zeros(K_dst.height * K_dst.width, np.float32)
    color_dst[lin[first]] = rgb[first]
    depth_dst[lin[first]] = z[first]
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


def main(argv: list[str] | None = None) -> int:
    """``python -m presim.capture.reprojection SRC TARGET:SOURCE ...``: MAE with poses vs no motion.

    SRC is a saved scene or any capture folder ``presim import`` reads; TARGET/SOURCE are frame ids
    (e.g. ``frame-000031``), bare frame numbers matched against the ids, or positions.
    """
    import argparse

    from presim.capture.store import is_scene_dir, load_scene

    ap = argparse.ArgumentParser(prog="python -m presim.capture.reprojection", description=main.__doc__)
    ap.add_argument("src")
    ap.add_argument("pairs", nargs="+", help="TARGET:SOURCE")
    args = ap.parse_args(argv)
    if is_scene_dir(args.src):
        scene = load_scene(args.src)
    else:
        from presim.capture.importers import import_capture

        scene = import_capture(args.src, align_floor=False)

    def resolve(tok: str) -> int:
        if tok in scene.frame_ids:
            return scene.frame_ids.index(tok)
        for i, fid in enumerate(scene.frame_ids):
            digits = "".join(ch for ch in fid if ch.isdigit())
            if digits and int(digits) == int(tok):
                return i
        return int(tok)

    rows = []
    for p in args.pairs:
        t, s = (resolve(x) for x in p.split(":"))
        m1, c1 = reprojection_mae(scene, t, s)
        m0, _ = reprojection_mae(scene, t, s, use_poses=False)
        rows.append((m1, m0, c1))
        print(f"{scene.frame_ids[t]} <- {scene.frame_ids[s]}: MAE with poses {m1:6.2f}  no motion {m0:6.2f}  "
              f"coverage {c1:.3f}")
    r = np.array(rows)
    print(f"mean: MAE with poses {r[:, 0].mean():.2f}  no motion {r[:, 1].mean():.2f}  coverage {r[:, 2].mean():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
