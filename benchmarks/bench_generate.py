"""Data generation costs: the built-in sample scene and ``presim gen-bop``, against same-run baselines.

Sub-commands:

- ``sample-scene``: median wall and CPU time of ``build_sample_scene`` (640x480, 60 frames default)
  after a warm-up build (numba compilation) against, as the baseline measured in the same run, the
  bare Open3D ray cast of the same frames (the ratio is the cost of shading + corruption + saving);
  ``render_ground_truth`` ms per view; reprojection colour errors between neighbouring frames
  (i -> i+1, grey levels): ``forward`` = ``presim.capture.reprojection.reprojection_mae``
  (nearest-pixel forward splat) and ``lookup`` = target pixels looked up in the source through the
  target depth where the source sees the same point (depth within 1 %), with the poses and with no
  motion, on the clean depth (``ground_truth/depth_clean.npy``) and on the corrupted sensor depth.
- ``gen-bop``: frames/s of ``presim gen-bop`` (``generate_bop``) with 1 and 2 local worker processes
  (and Ray with ``--ray``) on a small sample scene built once per run; one warm-up run per
  configuration, then ``--repeats`` timed runs into fresh folders; the ratio to the 1-worker
  baseline measured in the same run. Worker runs include process start-up (spawn + scene load +
  Renderer build), as a user's job does.

    python benchmarks/bench_generate.py sample-scene [--repeats 1] [--dst DIR] [--width 640 --height 480 --frames 60]
    python benchmarks/bench_generate.py gen-bop [--frames 12] [--width 640 --height 360] [--ray]
    python benchmarks/bench_generate.py sample-scene --quick       # smoke run (128x96, 4 frames)
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


# ---- sample-scene ------------------------------------------------------------------------------

def lookup_error(scene, t: int, s: int, use_poses: bool = True) -> np.ndarray:
    from presim.geometry import compose, invert, project, unproject_depth

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


def cmd_sample_scene(args) -> None:
    from presim.capture.reprojection import reprojection_mae
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene, clean_scene, render_view
    from presim.capture.store import load_scene

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
        render_view(0, cfg, scene.T_world_cam[0], K)  # warms the ray caster's caches
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



# ---- gen-bop -----------------------------------------------------------------------------------

def cmd_gen_bop(args) -> None:
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene
    from presim.capture.store import load_scene
    from presim.datasets.generate import GenConfig, generate_bop
    from presim.datasets.object_sources import resolve_objects

    tmp = Path(tempfile.mkdtemp(prefix="bench_gen_bop_"))
    try:
        scene_dir = build_sample_scene(tmp / "scene", seed=0, config=SampleSceneConfig(
            width=args.scene_width, height=args.scene_height, num_frames=args.scene_frames))
        objects = resolve_objects(load_scene(scene_dir), None)
        cfg = GenConfig(frames=args.frames, width=args.width, height=args.height, seed=0)
        runs = [("serial (1 process)", 1, None), ("2 worker processes", 2, None)]
        if args.ray:
            runs.append(("ray local, 2 actors", 2, "local"))
        print(f"scene {args.scene_width}x{args.scene_height}, {args.frames} frames at {args.width}x{args.height}, "
              f"cpu_count={os.cpu_count()}, load avg {os.getloadavg()[0]:.1f}")
        base = None
        for name, workers, ray in runs:
            times = []
            for rep in range(args.repeats + 1):
                out = tmp / f"out_{workers}_{ray}_{rep}"
                t0 = time.perf_counter()
                generate_bop(scene_dir, out, objects, cfg, workers=workers, ray_address=ray)
                dt = time.perf_counter() - t0
                shutil.rmtree(out, ignore_errors=True)
                if rep > 0:  # the first run is the warm-up
                    times.append(dt)
            fps = args.frames / statistics.median(times)
            base = base or fps
            print(f"{name:24s} median {statistics.median(times):7.2f} s  {fps:6.3f} frames/s  x{fps / base:.2f} vs serial")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("sample-scene", help="build time of the sample scene vs the bare ray cast; its errors")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--dst", type=Path, default=None, help="keep the built scene here")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--quick", action="store_true", help="smoke run: 128x96, 4 frames")
    p = sub.add_parser("gen-bop", help="gen-bop frames/s with 1 and 2 workers (and Ray)")
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--scene-width", type=int, default=320)
    p.add_argument("--scene-height", type=int, default=240)
    p.add_argument("--scene-frames", type=int, default=24)
    p.add_argument("--ray", action="store_true", help="also time --ray local with 2 actors")
    p.add_argument("--quick", action="store_true", help="smoke run: 4 frames of 64x48 from an 80x60 scene, 1 repeat")
    args = ap.parse_args(argv)
    if args.quick:
        args.width, args.height, args.frames = (128, 96, 4) if args.cmd == "sample-scene" else (64, 48, 4)
        if args.cmd == "gen-bop":
            args.scene_width, args.scene_height, args.scene_frames, args.repeats = 80, 60, 6, 1
    common.setup()
    (cmd_sample_scene if args.cmd == "sample-scene" else cmd_gen_bop)(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
