"""Peak memory per environment: resident set size after creation and the peak after N steps.

Each case runs in its own child process (the peak, VmHWM, is per process), on a saved scene:

- ``pointnav``: one ``PointNavEnv`` (the ``PreSim-PointNav-v0`` default 128x96 camera), random seeded
  actions; needs a scene with a floor;
- ``vector``: ``PointNavVectorEnv`` of ``--num-envs`` robots (one shared scene and renderer);
  per env = peak / N;
- ``vector-workers``: the same vector env with ``workers=2`` (robots split over two processes, each
  with its own scene and renderer); the peaks of the main process and of both workers are summed
  (an upper bound: each process's VmHWM may fall at a different time);
- ``vga``: the simulator with one 640x480 camera (``presim drive``'s default) visiting every
  captured view: the free camera rig placed, step by step, at the midpoint of consecutive captured
  poses (the worst case for the per-view cache: each step needs new views). Works on any scene.

Reported per case (MB = 2^20 bytes): ``rss_imported`` (Python + numpy/numba/... after the imports),
``rss_created`` (after building the env, before the first render), ``peak`` (VmHWM after the steps)
the peak of the private (anonymous) memory sampled after every step, and the renderer's point
cache. The scene's colour/depth arrays are memory-mapped (``presim.capture.
store``): their touched pages count in RSS but are page cache shared between processes.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_memory.py                       # sample scene, 100 frames
    PYTHONPATH=. .venv/bin/python benchmarks/bench_memory.py --scene /work/scenes/tum_r --frames 100 --cases vga
    PYTHONPATH=. .venv/bin/python benchmarks/bench_memory.py --json out/mem.json --cache-mb 256
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)

CASES = ("pointnav", "vector", "vector-workers", "vga")


def _status_mb(key: str, pid: int | str = "self") -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def child(args) -> dict:
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    import numpy as np

    from presim.capture.store import load_scene
    from presim.geometry import compose, invert
    from presim.sensors.camera import CameraSpec
    from presim.sim.controllers import Action
    from presim.sim.envs import PointNavEnv
    from presim.sim.robot import free_camera_rig
    from presim.sim.simulator import SimConfig, Simulator
    from presim.sim.vector_env import PointNavVectorEnv
    from presim.synthesis.renderer import RenderConfig, Renderer

    scene = load_scene(args.scene)
    if args.frames and args.frames < len(scene):
        scene = scene.subset(range(args.frames))
    rcfg = RenderConfig(cache_mb=args.cache_mb) if args.cache_mb else SimConfig().render  # the simulator's default
    out = {"case": args.child, "frames": len(scene), "rss_imported_mb": _status_mb("VmRSS")}
    rng = np.random.default_rng(0)
    anon = [0.0]

    def sample() -> None:  # private (anonymous) memory, sampled after every step
        anon[0] = max(anon[0], _status_mb("RssAnon"))

    if args.child == "pointnav":
        env = PointNavEnv(scene, renderer=Renderer(scene, rcfg) if args.cache_mb else None)
        out["rss_created_mb"] = _status_mb("VmRSS")
        env.reset(seed=0)
        for _ in range(args.steps):
            _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            if te or tr:
                env.reset()
            sample()
        renderer, n = env.sim.renderer, 1
    elif args.child == "vector":
        from presim.sim.vector_env import default_batch_backend

        venv = PointNavVectorEnv(scene, num_envs=args.num_envs,
                                 render=RenderConfig(backend=default_batch_backend(), cache_mb=rcfg.cache_mb))
        out["rss_created_mb"] = _status_mb("VmRSS")
        venv.reset(seed=0)
        for _ in range(args.steps):
            venv.step(rng.uniform(-1, 1, (args.num_envs, 2)).astype(np.float32))
            sample()
        renderer, n = venv.renderer, args.num_envs
    elif args.child == "vector-workers":
        venv = PointNavVectorEnv(args.scene if not args.frames else scene, num_envs=args.num_envs,
                                 render=RenderConfig(backend="numba", cache_mb=rcfg.cache_mb), workers=2)
        out["rss_created_mb"] = _status_mb("VmRSS")
        venv.reset(seed=0)
        for _ in range(args.steps):
            venv.step(rng.uniform(-1, 1, (args.num_envs, 2)).astype(np.float32))
            sample()
        workers = [_status_mb("VmHWM", pid) for pid in venv.worker_pids]
        anon_w = [_status_mb("RssAnon", pid) for pid in venv.worker_pids]
        n = args.num_envs
        out.update(peak_mb=_status_mb("VmHWM") + sum(workers), worker_peaks_mb=workers, rss_end_mb=_status_mb("VmRSS"),
                   num_envs=n, cache_mb=None, cached_views=-1, steps=args.steps,
                   peak_per_env_mb=(_status_mb("VmHWM") + sum(workers)) / n, peak_anon_mb=anon[0] + sum(anon_w),
                   peak_anon_per_env_mb=(anon[0] + sum(anon_w)) / n)
        venv.close()
        return out
    else:
        sim = Simulator(scene, free_camera_rig(), SimConfig(cameras=(CameraSpec(width=640, height=480),), render=rcfg))
        out["rss_created_mb"] = _status_mb("VmRSS")
        T_base_cam = invert(sim.T_base_cam(0))
        T = scene.T_world_cam
        sim.reset(0, start=compose(T[0], T_base_cam))
        for i in range(args.steps):
            a, b = T[i % len(T)], T[(i + 1) % len(T)]
            mid = a.copy()
            mid[:3, 3] = (a[:3, 3] + b[:3, 3]) / 2.0
            sim.step(Action(T_world_base=compose(mid, T_base_cam)))
            sample()
        renderer, n = sim.renderer, 1
    out.update(peak_mb=_status_mb("VmHWM"), rss_end_mb=_status_mb("VmRSS"), num_envs=n,
               cache_mb=renderer.cache_bytes / 2**20, cached_views=len(renderer.view_cache), steps=args.steps)
    out["peak_per_env_mb"] = out["peak_mb"] / n
    out["peak_anon_mb"] = anon[0]
    out["peak_anon_per_env_mb"] = anon[0] / n
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="saved scene (default: the sample scene, seed 0, 100 frames, built once "
                    "into the temp directory)")
    ap.add_argument("--frames", type=int, default=0, help="use the first N frames (0 = all)")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--cases", default="pointnav,vector,vga", help=f"comma list of {CASES}")
    ap.add_argument("--cache-mb", type=float, default=0.0, help="RenderConfig.cache_mb (0 = the default)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return 0
    if args.scene is None:
        from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

        args.scene = str(Path(tempfile.gettempdir()) / "presim_bench_memory_sample_seed0_640x480_100")
        if not (Path(args.scene) / "scene.json").is_file():
            build_sample_scene(args.scene, seed=0, config=SampleSceneConfig(num_frames=100), overwrite=True)
    print(f"scene {args.scene}  frames {args.frames or 'all'}  steps {args.steps}  load average {os.getloadavg()}")
    results = []
    for case in args.cases.split(","):
        if case not in CASES:
            raise SystemExit(f"--cases: unknown case {case!r} (choose from {', '.join(CASES)})")
        cmd = [sys.executable, __file__, "--child", case, "--scene", args.scene, "--frames", str(args.frames),
               "--steps", str(args.steps), "--num-envs", str(args.num_envs), "--cache-mb", str(args.cache_mb)]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            print(f"{case}: failed\n{p.stderr[-2000:]}", file=sys.stderr)
            continue
        r = json.loads(p.stdout.strip().splitlines()[-1])
        results.append(r)
        print(f"{case:9s} envs {r['num_envs']}  frames {r['frames']}  imported {r['rss_imported_mb']:6.0f} MB  "
              f"created {r['rss_created_mb']:6.0f} MB  peak {r['peak_mb']:6.0f} MB  per env {r['peak_per_env_mb']:6.0f} MB  "
              f"private (anon) peak {r['peak_anon_mb']:6.0f} MB = {r['peak_anon_per_env_mb']:5.0f}/env  "
              + (f"point cache {r['cache_mb']:5.0f} MB ({r['cached_views']} views)" if r["cached_views"] >= 0 else
                 f"workers' peaks {' + '.join(f'{w:.0f}' for w in r['worker_peaks_mb'])} MB"), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": args.scene, "results": results,
                                               "load_average_end": os.getloadavg()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
