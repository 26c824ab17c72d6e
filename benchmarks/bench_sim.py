"""Simulator throughput: steps/s with one 640x480 RGB-D camera in one process, aggregate steps/s with
N environments in parallel processes (N = 1, 2), and memory (RSS) per environment.

Baseline measured in the same run: the same step loop without a camera (control, collision, FK,
odometry only), so the ratio shows what rendering costs. Each figure is the median of ``--repeats``
runs after ``--warmup`` steps.

    .venv/bin/python benchmarks/bench_sim.py [--scene DIR] [--steps 20] [--repeats 3] [--procs 1 2]

Without ``--scene`` the built-in sample scene (seed 0, 640x480, 30 frames) is built once into a
cache folder in the temp directory and reused.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _scene_path(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    dst = Path(tempfile.gettempdir()) / "presim_bench_sim_sample_seed0_640x480_30"
    if not (dst / "scene.json").is_file():
        print(f"building the sample scene into {dst} (once) ...", flush=True)
        build_sample_scene(dst, seed=0, config=SampleSceneConfig(num_frames=30), overwrite=True)
    return dst


def _make_sim(scene_path: Path, width: int, height: int, camera: bool):
    from presim.capture.store import load_scene
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator

    cams = (CameraSpec(width=width, height=height, rate_hz=10.0),) if camera else ()
    return Simulator(load_scene(scene_path), None, SimConfig(dt_s=0.1, cameras=cams))


def _drive(sim, steps: int, seed: int) -> tuple[float, dict[str, float]]:
    """steps/s of ``steps`` steps of a gentle arc (stays inside the room; contacts are fine)."""
    stage: dict[str, list[float]] = {}
    t0 = time.perf_counter()
    for k in range(steps):
        r = sim.step(np.array([0.3, 0.0, 0.3 * np.sin(0.1 * k + seed)]))
        for key, v in r.timings_ms.items():
            stage.setdefault(key, []).append(v)
    dt = time.perf_counter() - t0
    return steps / dt, {k: statistics.median(v) for k, v in stage.items()}


def _worker(scene_path: str, width: int, height: int, warmup: int, steps: int, seed: int,
            barrier, out) -> None:
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    rss0 = _rss_mb()
    sim = _make_sim(Path(scene_path), width, height, camera=True)
    sim.reset(seed)
    _drive(sim, warmup, seed)
    barrier.wait()
    t0 = time.perf_counter()
    rate, _ = _drive(sim, steps, seed)
    out.put({"seed": seed, "t0": t0, "t1": time.perf_counter(), "steps": steps, "rate": rate,
             "rss_mb": _rss_mb(), "rss_import_mb": rss0})


def _parallel(scene_path: Path, n: int, width: int, height: int, warmup: int, steps: int) -> dict:
    ctx = mp.get_context("spawn")  # numba's threads do not survive fork
    barrier, out = ctx.Barrier(n), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(str(scene_path), width, height, warmup, steps, i, barrier, out))
             for i in range(n)]
    for p in procs:
        p.start()
    res = [out.get() for _ in procs]
    for p in procs:
        p.join()
    wall = max(r["t1"] for r in res) - min(r["t0"] for r in res)
    return {"aggregate": sum(r["steps"] for r in res) / wall, "rss_mb": [r["rss_mb"] for r in res]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=None, help="saved scene folder (default: cached sample scene)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--procs", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    scene_path = _scene_path(args.scene)
    print(f"scene {scene_path}  camera {args.width}x{args.height}  cpus {os.cpu_count()}  "
          f"load avg {os.getloadavg()[0]:.1f}", flush=True)

    # Baseline in the same run: the loop without a camera.
    rss_before = _rss_mb()
    base = _make_sim(scene_path, args.width, args.height, camera=False)
    base.reset(0)
    _drive(base, args.warmup, 0)
    base_rates = [_drive(base, args.steps * 5, r)[0] for r in range(args.repeats)]

    sim = _make_sim(scene_path, args.width, args.height, camera=True)
    sim.reset(0)
    _drive(sim, args.warmup, 0)
    runs = [_drive(sim, args.steps, r) for r in range(args.repeats)]
    rates = [r for r, _ in runs]
    stages = runs[len(runs) // 2][1]
    rss_after = _rss_mb()
    med, med_base = statistics.median(rates), statistics.median(base_rates)
    print(f"no camera (baseline)      : {med_base:8.1f} steps/s  (median of {args.repeats})")
    print(f"one {args.width}x{args.height} RGB-D camera: {med:8.2f} steps/s  (median of {args.repeats}; "
          f"runs {', '.join(f'{r:.2f}' for r in rates)})  = {med / med_base:.4f} x baseline")
    print("  median ms per stage: " + "  ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    print(f"  RSS of this process: {rss_before:.0f} MB before the simulators, {rss_after:.0f} MB after "
          f"(2 simulators)")

    one = None
    for n in args.procs:
        aggs, rss = [], []
        for _ in range(args.repeats):
            r = _parallel(scene_path, n, args.width, args.height, args.warmup, args.steps)
            aggs.append(r["aggregate"])
            rss += r["rss_mb"]
        agg = statistics.median(aggs)
        one = one or agg
        print(f"{n} env process(es)         : {agg:8.2f} steps/s aggregate (median of {args.repeats})  "
              f"= {agg / one:.2f} x N=1;  RSS per env {statistics.median(rss):.0f} MB")


if __name__ == "__main__":
    main()
