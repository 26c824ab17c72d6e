"""Simulator and environment throughput and memory, each against a baseline measured in the same run.

Sub-commands (scene: ``--scene DIR``, a saved scene with a floor; default: the built-in sample scene,
seed 0, 640x480, built once into the benchmarks' cache folder):

- ``steps``: steps/s of the simulator with one RGB-D camera (640x480 default) in one process against
  the same step loop without a camera (control, collision, FK, odometry only: the ratio is what
  rendering costs), median per stage; aggregate steps/s with N simulators in parallel processes
  (``--procs 1 2``) and the RSS per process.
- ``envs``: ``PreSim-PointNav-v0`` (``PointNavEnv``, 128x96) steps/s against the same env with
  ``RenderConfig(lod_levels=0, reuse_move_m=0)`` ("today"); ``PointNavVectorEnv`` of ``--num-envs``
  robots per renderer variant (``--vector``: ``numba``, ``numba-1-thread`` = ``PerfConfig(threads=1)``,
  ``numba-workers`` = robots split over max(2, cores) processes, ``torch``) as env-steps/s and the
  ratio to the single env (also the median of per-repeat ratios); the demo drive (default robot, one
  640x480 camera at 10 Hz, the built-in seeded route) new vs today. Every env takes one untimed step,
  then ``--warmup-steps`` timed steps (the cold rate: views met for the first time are prepared),
  then ``--repeats`` measured blocks, the order rotated per repeat. ``--warmup-steps 200`` measures
  the steady state of a long run (cache full; views still rebuilt when the cache evicts).
- ``memory``: peak memory per environment, each case in its own child process (VmHWM is per
  process): ``pointnav``; ``vector`` (``--num-envs`` robots, one renderer; per env = peak / N);
  ``vector-workers`` (workers=2; main and worker peaks summed, an upper bound); ``vga`` (the
  simulator with one 640x480 camera placed at the midpoint of consecutive captured poses, step by
  step: the worst case for the per-view cache). Reports RSS after the imports, after building the
  env, the peak (VmHWM), the peak of private (anonymous) memory sampled after every step and the
  renderer's point cache (MiB). The scene's arrays are memory-mapped: touched pages count in RSS
  but are page cache shared between processes.

    python benchmarks/bench_sim.py steps [--scene DIR] [--steps 20] [--repeats 3] [--procs 1 2]
    python benchmarks/bench_sim.py envs --scene out/sample --json out/envs.json
    python benchmarks/bench_sim.py envs --warmup-steps 200 --vector numba,numba-workers
    python benchmarks/bench_sim.py memory --frames 100 --cases pointnav,vector,vga --json out/mem.json
    python benchmarks/bench_sim.py steps --quick        # smoke run (tiny scene, few steps)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402

TODAY = dict(lod_levels=0, reuse_move_m=0.0)
QUICK_SCENE = dict(frames=6, width=160, height=120)
"""The sample scene of ``--quick`` runs (small: built in seconds)."""


def _scene_folder(args) -> str:
    if args.scene:
        return args.scene
    if args.quick:
        return str(common.sample_scene(**QUICK_SCENE))
    return str(common.sample_scene(frames=getattr(args, "scene_frames", 30)))


# ---- steps: the simulator loop with and without a camera -------------------------------------

def _make_sim(scene_path: str, width: int, height: int, camera: bool):
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
    return steps / (time.perf_counter() - t0), {k: statistics.median(v) for k, v in stage.items()}


def _worker(scene_path: str, width: int, height: int, warmup: int, steps: int, seed: int, barrier, out) -> None:
    common.setup()
    sim = _make_sim(scene_path, width, height, camera=True)
    sim.reset(seed)
    _drive(sim, warmup, seed)
    barrier.wait()
    t0 = time.perf_counter()
    rate, _ = _drive(sim, steps, seed)
    out.put({"t0": t0, "t1": time.perf_counter(), "steps": steps, "rate": rate, "rss_mb": common.status_mb("VmRSS")})


def _parallel(scene_path: str, n: int, width: int, height: int, warmup: int, steps: int) -> dict:
    ctx = mp.get_context("spawn")  # numba's threads do not survive fork
    barrier, out = ctx.Barrier(n), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(scene_path, width, height, warmup, steps, i, barrier, out))
             for i in range(n)]
    for p in procs:
        p.start()
    res = [out.get() for _ in procs]
    for p in procs:
        p.join()
    wall = max(r["t1"] for r in res) - min(r["t0"] for r in res)
    return {"aggregate": sum(r["steps"] for r in res) / wall, "rss_mb": [r["rss_mb"] for r in res]}


def cmd_steps(args) -> dict:
    scene_path = _scene_folder(args)
    common.header(scene=scene_path, camera=f"{args.width}x{args.height}")
    rss_before = common.status_mb("VmRSS")
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
    rss_after = common.status_mb("VmRSS")
    med, med_base = statistics.median(rates), statistics.median(base_rates)
    print(f"no camera (baseline)      : {med_base:8.1f} steps/s  (median of {args.repeats})")
    print(f"one {args.width}x{args.height} RGB-D camera: {med:8.2f} steps/s  (median of {args.repeats}; "
          f"runs {', '.join(f'{r:.2f}' for r in rates)})  = {med / med_base:.4f} x baseline")
    print("  median ms per stage: " + "  ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    print(f"  RSS of this process: {rss_before:.0f} MB before the simulators, {rss_after:.0f} MB after (2 simulators)")
    res = {"scene": scene_path, "no_camera_steps_per_s": med_base, "camera_steps_per_s": med,
           "ratio_vs_no_camera": med / med_base, "stages_ms_median": stages, "procs": {}}
    one = None
    for n in args.procs:
        aggs, rss = [], []
        for _ in range(args.repeats):
            r = _parallel(scene_path, n, args.width, args.height, args.warmup, args.steps)
            aggs.append(r["aggregate"])
            rss += r["rss_mb"]
        agg = statistics.median(aggs)
        one = one or agg
        res["procs"][str(n)] = {"aggregate_steps_per_s": agg, "ratio_vs_one": agg / one, "rss_mb_median": statistics.median(rss)}
        print(f"{n} env process(es)         : {agg:8.2f} steps/s aggregate (median of {args.repeats})  "
              f"= {agg / one:.2f} x N=1;  RSS per env {statistics.median(rss):.0f} MB")
    return res


# ---- envs: PointNav single / vector / demo drive -----------------------------------------------

VECTORS = ("numba", "numba-1-thread", "numba-workers", "torch")


def cmd_envs(args) -> dict:
    from presim.capture.store import load_scene
    from presim.sensors.camera import CameraSpec
    from presim.sim.envs import PointNavEnv
    from presim.sim.robot import default_robot
    from presim.sim.routes import RouteDriver, ground_route
    from presim.sim.simulator import SIM_RENDER_CACHE_MB, SimConfig, Simulator
    from presim.sim.vector_env import PointNavVectorEnv
    from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

    scene_path = _scene_folder(args)
    scene = load_scene(scene_path)
    common.header(scene=scene_path)
    sim_perf = PerfConfig(cache_mb=SIM_RENDER_CACHE_MB)
    steppers: dict[str, tuple] = {}  # name -> (step function, env-steps per call)
    envs = {"new": PointNavEnv(scene),
            "today": PointNavEnv(scene, renderer=Renderer(scene, RenderConfig(**TODAY), sim_perf))}
    for name, env in envs.items():
        env.reset(seed=0)
        rng = np.random.default_rng(0)

        def step(env=env, rng=rng):
            _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            if te or tr:
                env.reset()
        steppers[name] = (step, 1)
    workers = max(2, os.cpu_count() or 1)
    variants = {"numba": ({}, 0), "numba-1-thread": ({"threads": 1}, 0), "numba-workers": ({}, workers),
                "torch": ({"backend": "torch"}, 0)}
    venvs = {}
    for v in (v for v in args.vector.split(",") if v):
        perf_kw, nproc = variants[v]
        venv = PointNavVectorEnv(scene if not nproc else scene_path, num_envs=args.num_envs, workers=nproc,
                                 perf=PerfConfig(cache_mb=SIM_RENDER_CACHE_MB, **perf_kw))
        venv.reset(seed=0)
        rng = np.random.default_rng(0)

        def vstep(venv=venv, rng=rng):
            venv.step(rng.uniform(-1, 1, (args.num_envs, 2)).astype(np.float32))
        name = f"numba {nproc} workers" if nproc else v
        venvs[name] = venv
        steppers[name] = (vstep, args.num_envs)
    cold = {}
    for name, (step, per) in steppers.items():
        step()  # untimed: loads the compiled kernels
        wall, cpu, _ = common.timed(lambda: [step() for _ in range(args.warmup_steps)])
        cold[name] = args.warmup_steps * per / wall * 1e3
    rates = {name: [] for name in steppers}
    cpu = {name: [] for name in steppers}
    order = list(steppers)
    for rep in range(args.repeats):
        for name in order[rep % len(order):] + order[:rep % len(order)]:  # rotated: no fixed position
            step, per = steppers[name]
            wall, c, _ = common.timed(lambda: [step() for _ in range(args.steps)])
            rates[name].append(args.steps * per / wall * 1e3)
            cpu[name].append(c / args.steps / per)
    res: dict[str, dict] = {}
    single, today = statistics.median(rates["new"]), statistics.median(rates["today"])
    r1 = res["pointnav single"] = {
        "steps_per_s_median": single, "today_steps_per_s_median": today, "speedup_vs_today": single / today,
        "runs": rates["new"], "today_runs": rates["today"], "cpu_ms_per_step_median": statistics.median(cpu["new"]),
        "today_cpu_ms_per_step_median": statistics.median(cpu["today"]), "warmup_steps": args.warmup_steps,
        "cold_steps_per_s": cold["new"], "today_cold_steps_per_s": cold["today"]}
    print(f"PointNav single env 128x96 : {single:7.1f} steps/s   today {today:7.1f}  -> x{r1['speedup_vs_today']:.2f}   "
          f"CPU ms/step {r1['cpu_ms_per_step_median']:.1f} vs today {r1['today_cpu_ms_per_step_median']:.1f}   "
          f"(first {args.warmup_steps} steps: {cold['new']:.1f}, today {cold['today']:.1f})", flush=True)
    for name, venv in venvs.items():
        med = statistics.median(rates[name])
        pair = statistics.median(v / s for v, s in zip(rates[name], rates["new"]))  # same round, same load
        res[f"pointnav vector {args.num_envs} {name}"] = {
            "env_steps_per_s_median": med, "ratio_vs_single": med / single, "ratio_vs_single_paired_median": pair,
            "runs": rates[name], "cpu_ms_per_env_step_median": statistics.median(cpu[name]),
            "worker_processes": venv.workers, "cold_env_steps_per_s": cold[name],
            "cold_ratio_vs_single": cold[name] / cold["new"]}
        print(f"PointNav vector env x{args.num_envs} ({name:15s}): {med:7.1f} env-steps/s  = x{med / single:.2f} "
              f"the single env (paired x{pair:.2f})   CPU ms/env-step {statistics.median(cpu[name]):.1f} (this "
              f"process only)   (first {args.warmup_steps} steps: {cold[name]:.1f})", flush=True)
        venv.close()
    sims = {}
    for name, rc in (("new", RenderConfig()), ("today", RenderConfig(**TODAY))):
        sim = Simulator(scene, default_robot(), SimConfig(dt_s=0.1, cameras=(CameraSpec(width=640, height=480,
                                                                                         rate_hz=10.0),), render=rc))
        sim.reset(0)
        drv = RouteDriver(ground_route(sim, np.random.default_rng(0)), sim)
        sim.step(drv.action(sim))
        sims[name] = (lambda sim=sim, drv=drv: sim.step(drv.action(sim)))
    times = common.alternate({k: (lambda f=f: [f() for _ in range(args.drive_steps)]) for k, f in sims.items()},
                             args.repeats)
    rate = {k: [args.drive_steps / w * 1e3 for w, _ in v] for k, v in times.items()}
    d_new, d_old = statistics.median(rate["new"]), statistics.median(rate["today"])
    cpu_d = {k: statistics.median(c / args.drive_steps for _, c in v) for k, v in times.items()}
    res["demo drive 640x480"] = {"steps_per_s_median": d_new, "today_steps_per_s_median": d_old,
                                 "speedup_vs_today": d_new / d_old, "runs": rate["new"], "today_runs": rate["today"],
                                 "cpu_ms_per_step_median": cpu_d["new"], "today_cpu_ms_per_step_median": cpu_d["today"]}
    print(f"demo drive 640x480         : {d_new:7.2f} steps/s   today {d_old:7.2f}  -> x{d_new / d_old:.2f}   "
          f"CPU ms/step {cpu_d['new']:.1f} vs today {cpu_d['today']:.1f}")
    print(f"peak RSS {common.peak_rss_mb():.0f} MB (all envs of this process)")
    return {"scene": scene_path, "results": res, "peak_rss_mb": common.peak_rss_mb()}


# ---- memory: one child process per case ------------------------------------------------------

CASES = ("pointnav", "vector", "vector-workers", "vga")


def memory_child(args) -> dict:
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
    perf = SimConfig().perf  # the simulator's default (bounded cache)
    if args.cache_mb:
        import dataclasses

        perf = dataclasses.replace(perf, cache_mb=args.cache_mb)
    out = {"case": args.child, "frames": len(scene), "rss_imported_mb": common.status_mb("VmRSS")}
    rng = np.random.default_rng(0)
    anon = [0.0]

    def sample() -> None:  # private (anonymous) memory, sampled after every step
        anon[0] = max(anon[0], common.status_mb("RssAnon"))

    if args.child == "pointnav":
        env = PointNavEnv(scene, renderer=Renderer(scene, RenderConfig(), perf) if args.cache_mb else None)
        out["rss_created_mb"] = common.status_mb("VmRSS")
        env.reset(seed=0)
        for _ in range(args.steps):
            _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            if te or tr:
                env.reset()
            sample()
        renderer, n = env.sim.renderer, 1
    elif args.child in ("vector", "vector-workers"):
        workers = 2 if args.child == "vector-workers" else 0
        venv = PointNavVectorEnv(args.scene if workers and not args.frames else scene, num_envs=args.num_envs,
                                 perf=perf, workers=workers)
        out["rss_created_mb"] = common.status_mb("VmRSS")
        venv.reset(seed=0)
        for _ in range(args.steps):
            venv.step(rng.uniform(-1, 1, (args.num_envs, 2)).astype(np.float32))
            sample()
        n = args.num_envs
        if workers:
            peaks = [common.status_mb("VmHWM", pid) for pid in venv.worker_pids]
            anon_w = [common.status_mb("RssAnon", pid) for pid in venv.worker_pids]
            total = common.status_mb("VmHWM") + sum(peaks)
            out.update(peak_mb=total, worker_peaks_mb=peaks, rss_end_mb=common.status_mb("VmRSS"), num_envs=n,
                       cache_mb=None, cached_views=-1, steps=args.steps, peak_per_env_mb=total / n,
                       peak_anon_mb=anon[0] + sum(anon_w), peak_anon_per_env_mb=(anon[0] + sum(anon_w)) / n)
            venv.close()
            return out
        renderer = venv.renderer
    else:
        sim = Simulator(scene, free_camera_rig(), SimConfig(cameras=(CameraSpec(width=640, height=480),), perf=perf))
        out["rss_created_mb"] = common.status_mb("VmRSS")
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
    out.update(peak_mb=common.status_mb("VmHWM"), rss_end_mb=common.status_mb("VmRSS"), num_envs=n,
               cache_mb=renderer.executor.cache.nbytes / 2**20, cached_views=len(renderer.executor.cache), steps=args.steps)
    out.update(peak_per_env_mb=out["peak_mb"] / n, peak_anon_mb=anon[0], peak_anon_per_env_mb=anon[0] / n)
    return out


def cmd_memory(args) -> dict:
    if args.child:
        print(json.dumps(memory_child(args)))
        return {}
    args.scene = args.scene or (str(common.sample_scene(**QUICK_SCENE)) if args.quick
                                else str(common.sample_scene(frames=100)))
    common.header(scene=args.scene, frames=args.frames or "all", steps=args.steps)
    results = []
    for case in args.cases.split(","):
        if case not in CASES:
            raise SystemExit(f"--cases: unknown case {case!r} (choose from {', '.join(CASES)})")
        cmd = [sys.executable, __file__, "memory", "--child", case, "--scene", args.scene, "--frames",
               str(args.frames), "--steps", str(args.steps), "--num-envs", str(args.num_envs),
               "--cache-mb", str(args.cache_mb)]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"{case}: failed\n{p.stderr[-2000:]}")
        r = json.loads(p.stdout.strip().splitlines()[-1])
        results.append(r)
        print(f"{case:14s} envs {r['num_envs']}  frames {r['frames']}  imported {r['rss_imported_mb']:6.0f} MB  "
              f"created {r['rss_created_mb']:6.0f} MB  peak {r['peak_mb']:6.0f} MB  per env {r['peak_per_env_mb']:6.0f} MB  "
              f"private (anon) peak {r['peak_anon_mb']:6.0f} MB = {r['peak_anon_per_env_mb']:5.0f}/env  "
              + (f"point cache {r['cache_mb']:5.0f} MB ({r['cached_views']} views)" if r["cached_views"] >= 0 else
                 f"workers' peaks {' + '.join(f'{w:.0f}' for w in r['worker_peaks_mb'])} MB"), flush=True)
    return {"scene": args.scene, "results": results}


# ---- main --------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)

    def common_args(p, steps: int) -> None:
        p.add_argument("--scene", help="saved scene folder with a floor (default: the sample scene, built once)")
        p.add_argument("--steps", type=int, default=steps, help="steps per measured repeat")
        p.add_argument("--json", help="write the results here")
        p.add_argument("--quick", action="store_true", help="smoke run: a tiny sample scene and few steps")

    p = sub.add_parser("steps", help="simulator steps/s with a camera vs without, N processes")
    common_args(p, 20)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--procs", type=int, nargs="*", default=[1, 2], help="parallel simulator processes per case")
    p = sub.add_parser("envs", help="PointNav single / vector env and the demo drive, new vs today")
    common_args(p, 20)
    p.add_argument("--warmup-steps", type=int, default=3,
                   help="timed steps before the measured repeats (the cold rate); 200 = steady state of a long run")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--drive-steps", type=int, default=10)
    p.add_argument("--vector", default="numba,numba-1-thread,numba-workers",
                   help=f"vector env renderers, comma-separated, of {', '.join(VECTORS)} ('' = none)")
    p = sub.add_parser("memory", help="peak memory per environment, one child process per case")
    common_args(p, 100)
    p.add_argument("--frames", type=int, default=0, help="use the first N frames (0 = all)")
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--cases", default="pointnav,vector,vga", help=f"comma list of {', '.join(CASES)}")
    p.add_argument("--cache-mb", type=float, default=0.0, help="PerfConfig.cache_mb (0 = the simulator's default)")
    p.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.steps = 2
        if args.cmd == "steps":
            args.width, args.height, args.warmup, args.repeats, args.procs = 64, 48, 1, 1, [1]
        elif args.cmd == "envs":
            args.warmup_steps, args.repeats, args.num_envs, args.drive_steps = 1, 1, 2, 1
            args.vector = "numba"
        else:
            args.num_envs, args.cases = 2, "pointnav"
    for name in ("steps", "warmup_steps", "repeats", "num_envs", "drive_steps"):
        if getattr(args, name, 1) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.cmd == "envs" and any(v and v not in VECTORS for v in args.vector.split(",")):
        ap.error(f"--vector: unknown renderer in {args.vector!r} ({', '.join(VECTORS)})")
    common.setup()
    res = {"steps": cmd_steps, "envs": cmd_envs, "memory": cmd_memory}[args.cmd](args)
    if res and not getattr(args, "child", None):
        common.write_json(args.json, {**res, "load_average_end": os.getloadavg()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
