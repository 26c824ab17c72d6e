"""Views prepared ahead (``RenderConfig.prefetch``) against none, in one process: PointNav and the demo drive.

Two identical environments (one with the view cache's background thread, one without) are stepped
in alternating blocks from their start (the cold part of a run is where new views are met), with
the simulator's default cache bound. Reported per case: the mean wall ms per step (total time /
steps: what the throughput sees, including the steps that stall on a new view), the median of the
block means, the ratio off / on of the means, and the views the main thread and the background
thread prepared.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_prefetch.py --scene /work/scenes/sample
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def _pointnav(scene, prefetch: bool):
    from presim.sim.envs import PointNavEnv
    from presim.sim.simulator import SIM_RENDER_CACHE_MB
    from presim.synthesis.renderer import RenderConfig, Renderer

    r = Renderer(scene, RenderConfig(prefetch=prefetch, cache_mb=SIM_RENDER_CACHE_MB))
    env = PointNavEnv(scene, renderer=r)
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def step():
        _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        if te or tr:
            env.reset()
    return step, r


def _drive(scene, prefetch: bool):
    from presim.sensors.camera import CameraSpec
    from presim.sim.robot import default_robot
    from presim.sim.routes import RouteDriver, ground_route
    from presim.sim.simulator import SIM_RENDER_CACHE_MB, SimConfig, Simulator
    from presim.synthesis.renderer import RenderConfig

    sim = Simulator(scene, default_robot(), SimConfig(
        dt_s=0.1, cameras=(CameraSpec(width=640, height=480, rate_hz=10.0),),
        render=RenderConfig(prefetch=prefetch, cache_mb=SIM_RENDER_CACHE_MB)))
    sim.reset(0)
    drv = RouteDriver(ground_route(sim, np.random.default_rng(0)), sim)
    return (lambda: sim.step(drv.action(sim))), sim.renderer


def _count_main_builds(renderer) -> list[int]:
    """Counts the views ``renderer`` builds in the calling (main) thread from now on."""
    n = [0]
    build = renderer._build_view

    def counted(idx, level, parallel=True):
        if parallel:
            n[0] += 1
        return build(idx, level, parallel)
    renderer._build_view = counted
    return n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="saved scene with a floor (default: the sample scene, seed 0, 30 frames, built "
                    "once in the temp folder, as benchmarks/bench_pointnav.py)")
    ap.add_argument("--blocks", type=int, default=12, help="measured blocks per configuration")
    ap.add_argument("--pointnav-steps", type=int, default=20, help="PointNav steps per block")
    ap.add_argument("--drive-steps", type=int, default=8, help="drive steps per block")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    from bench_pointnav import load_sim_scene  # this folder is on sys.path when run as a script

    args.scene, scene = load_sim_scene(args.scene)
    print(f"scene {args.scene}  load average {os.getloadavg()}", flush=True)
    res = {}
    for case, make, n in (("pointnav 128x96", _pointnav, args.pointnav_steps), ("demo drive 640x480", _drive,
                                                                               args.drive_steps)):
        runs = {name: make(scene, name == "on") for name in ("on", "off")}
        builds = {name: _count_main_builds(r) for name, (_, r) in runs.items()}
        for step, _ in runs.values():
            step()  # first frame (and any compilation) outside the measurement
        blocks: dict[str, list[float]] = {"on": [], "off": []}
        for b in range(args.blocks):
            for name in (("on", "off") if b % 2 == 0 else ("off", "on")):
                step = runs[name][0]
                t0 = time.perf_counter()
                for _ in range(n):
                    step()
                blocks[name].append((time.perf_counter() - t0) * 1e3 / n)
        runs["on"][1].view_cache.wait()
        mean = {k: statistics.fmean(v) for k, v in blocks.items()}
        med = {k: statistics.median(v) for k, v in blocks.items()}
        cache = runs["on"][1].view_cache
        res[case] = {"mean_ms": mean, "median_block_ms": med, "ratio_off_over_on": mean["off"] / mean["on"],
                     "main_thread_builds": {k: v[0] for k, v in builds.items()},
                     "built_ahead": cache.built_ahead, "taken_ahead": cache.taken_ahead,
                     "steps": args.blocks * n}
        print(f"{case:20s} mean wall ms/step: prefetch on {mean['on']:6.2f}  off {mean['off']:6.2f}  -> x"
              f"{mean['off'] / mean['on']:.3f}   median block: {med['on']:6.2f} / {med['off']:6.2f}   "
              f"views built by the main thread {builds['on'][0]} / {builds['off'][0]}, ahead {cache.built_ahead} "
              f"(taken {cache.taken_ahead})   load {os.getloadavg()[0]:.1f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": args.scene, "results": res}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
