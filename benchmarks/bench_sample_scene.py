"""Benchmark and accuracy check of the built-in sample scene (presim.capture.sample_scene).

Prints
- the median wall and CPU time of ``build_sample_scene`` at the default size (640x480, 60 frames)
  after a warm-up build (numba compilation) and, as a baseline measured in the same run, the time of
  the bare Open3D ray cast of the same frames (shading + corruption + saving cost = the ratio);
- reprojection color errors between neighbouring frames (i -> i+1), gray levels:
  ``forward`` = presim.capture.reprojection.reprojection_mae (nearest-pixel forward splat),
  ``lookup`` = target pixels looked up in the source through the target depth where the source sees
  the same point (depth agrees within 1 %), with the poses and with no motion, on the clean depth
  (ground_truth/depth_clean.npy) and on the corrupted sensor depth (depth.npy).

    .venv/bin/python benchmarks/bench_sample_scene.py [--repeats 1] [--dst DIR] [--width 640 --height 480 --frames 60]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.reprojection import reprojection_mae  # noqa: E402
from presim.capture.sample_scene import (  # noqa: E402
    SampleSceneConfig, build_sample_scene, clean_scene, render_view,
)
from presim.capture.store import load_scene  # noqa: E402
from presim.geometry import compose, invert, project, unproject_depth  # noqa: E402


def lookup_error(scene, t: int, s: int, use_poses: bool = True) -> np.ndarray:
    ft, fs = scene.frame(t), scene.frame(s)
    T = compose(invert(fs.T_world_cam), ft.T_world_cam) if use_poses else np.eye(4)
    pts, mask = unproject_depth(ft.K, ft.depth_m, T)
    uv, z = project(fs.K, pts)
    ok = np.isfinite(uv).all(1)
    u = np.rint(np.where(ok, uv[:, 0], -1)).astype(int)
    v = np.rint(np.where(ok, uv[:, 1], -1)).astype(int)
    ok &= (u >= 0) & (u < fs.K.width) & (v >= 0) & (v < fs.K.height)
    ok[ok] &= np.abs(fs.depth_m[v[ok], u[ok]] - z[ok]) < 0.01 * z[ok]
    return np.abs(ft.color[mask][ok].astype(np.float32) - fs.color[v[ok], u[ok]].astype(np.float32)).mean(1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--dst", type=Path, default=None, help="keep the built scene here")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    cfg = dataclasses.replace(SampleSceneConfig(), width=args.width, height=args.height, num_frames=args.frames)
    tmp = Path(tempfile.mkdtemp(prefix="bench_sample_"))
    try:
        build_sample_scene(tmp / "warmup", seed=0, config=dataclasses.replace(cfg, width=64, height=48, num_frames=3))
        walls, cpus = [], []
        dst = args.dst or tmp / "scene"
        for _ in range(args.repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            build_sample_scene(dst, seed=0, config=cfg, overwrite=True)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
        scene = load_scene(dst)
        # Baseline: the bare ray cast of the same frames (Open3D), same process.
        from presim.capture.sample_scene.render import pixel_rays, scene_raycaster

        model = scene_raycaster(0, cfg)
        import open3d as o3d

        K = scene.intrinsics[0]
        w0 = time.perf_counter()
        for T in scene.T_world_cam:
            d = pixel_rays(K) @ T[:3, :3].T
            rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], 1).astype(np.float32)
            model.rc.cast_rays(o3d.core.Tensor(rays))
        cast_s = time.perf_counter() - w0
        wall = statistics.median(walls)
        print(f"build {cfg.width}x{cfg.height}, {cfg.num_frames} frames: median wall {wall:.2f} s, "
              f"CPU {statistics.median(cpus):.2f} s over {args.repeats} run(s); bare ray cast of the frames "
              f"{cast_s:.2f} s (ratio build/ray cast {wall / cast_s:.1f}x)")
        one = render_view(0, cfg, scene.T_world_cam[0], K)  # noqa: F841 (cache warm)
        ws = []
        for T in scene.T_world_cam[:10]:
            w0 = time.perf_counter()
            render_view(0, cfg, T, K)
            ws.append(time.perf_counter() - w0)
        print(f"render_ground_truth: median {statistics.median(ws) * 1e3:.0f} ms per {K.width}x{K.height} view")

        clean = clean_scene(dst)
        for name, sc in (("clean", clean), ("corrupted", scene)):
            fw, fw0, lk, lk_med, lk0 = [], [], [], [], []
            for i in range(len(sc) - 1):
                fw.append(reprojection_mae(sc, i + 1, i)[0])
                fw0.append(reprojection_mae(sc, i + 1, i, use_poses=False)[0])
                e = lookup_error(sc, i + 1, i)
                lk.append(e.mean())
                lk_med.append(np.median(e))
                lk0.append(np.abs(sc.frame(i + 1).color.astype(np.float32) - sc.frame(i).color).mean())
            print(f"{name:9s} depth, {len(fw)} neighbour pairs: forward MAE with poses {np.nanmean(fw):.2f} "
                  f"(median pair {np.nanmedian(fw):.2f}) vs no motion {np.nanmean(fw0):.2f}; lookup MAE "
                  f"{np.mean(lk):.2f}, median pixel error {np.median(lk_med):.2f} vs no motion {np.mean(lk0):.2f}")
        raw = np.asarray(scene.frames.depth_m)
        gt = np.asarray(clean.frames.depth_m)
        print(f"corrupted depth: {100 * (1 - (raw > 0).sum() / (gt > 0).sum()):.1f} % of surface pixels missing")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
