"""Throughput of ``presim gen-bop``: frames/s with 1 and 2 local worker processes (and Ray, optional).

Builds a small sample scene once, then generates the same dataset several times into fresh folders.
Each configuration: one warm-up run (numba compile caches, imports), then ``--repeats`` timed runs;
prints the median frames/s and the ratio to the 1-worker baseline measured in the same run. Worker
runs include process start-up (spawn + scene load + Renderer build), as a user's job does.

    .venv/bin/python benchmarks/bench_gen_bop.py [--frames 12] [--width 640 --height 360] [--ray]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--scene-width", type=int, default=320)
    ap.add_argument("--scene-height", type=int, default=240)
    ap.add_argument("--ray", action="store_true", help="also time --ray local with 2 actors")
    args = ap.parse_args()

    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene
    from presim.capture.store import load_scene
    from presim.datasets.generate import GenConfig, generate_bop
    from presim.datasets.object_sources import resolve_objects

    tmp = Path(tempfile.mkdtemp(prefix="bench_gen_bop_"))
    try:
        scene_dir = build_sample_scene(tmp / "scene", seed=0, config=SampleSceneConfig(
            width=args.scene_width, height=args.scene_height, num_frames=24))
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


if __name__ == "__main__":
    main()
