"""Environment throughput in one run: PointNav single env, PointNav vector env of N, the demo drive.

Every figure is measured beside its baseline in the same run, repeats alternating between the
configurations (so load changes on a shared machine hit both), medians reported. The single envs
and the vector envs are all built first; each repeat then measures every one of them in turn (the
order rotated per repeat), and the vector env's ratio to the single env is also given as the median
of the per-repeat ratios (``ratio_vs_single_paired_median``):

- ``pointnav single``: ``PreSim-PointNav-v0`` (``PointNavEnv``, default 128x96 camera) steps/s with
  random (seeded) actions; baseline = the same env with the pre-LOD renderer
  (``RenderConfig(lod_levels=0, reuse_move_m=0)``, "today").
- ``pointnav vector N``: :class:`presim.sim.vector_env.PointNavVectorEnv` env-steps/s (N robots
  per step), with ``torch_batch`` (one batch per step), with ``numba`` (frames spread over
  ``RenderConfig.batch_threads`` = auto threads), with ``numba 1 thread`` (frames one after
  another) and with ``numba W workers`` (``workers=W`` = max(2, cores) processes, each rendering
  its robots one after another); ratio to the single env. CPU ms per env-step counts this process
  only, so for the workers it is the main process's share, not the workers'. Each robot takes as
  many steps as the single env's robot (``--warmup-steps``, then ``--steps`` per repeat), so both
  meet new capture views at the same rate.
- **Cold and steady state.** Every env first takes one untimed step (it loads the compiled
  kernels), then ``--warmup-steps`` timed steps (default 3), reported as ``cold_steps_per_s``
  (single env) / ``cold_env_steps_per_s`` (vector env): that rate includes preparing the capture
  views the robot meets for the first time (the per-view cache fills) and is what a short run sees.
  With ``--warmup-steps 200`` the measured repeats are the steady state of a long run (an RL job's
  millions of steps): the cache is full, and views are still rebuilt when it evicts (its bound,
  ``SIM_RENDER_CACHE_MB``, holds).
- ``demo drive``: the simulator loop of ``presim demo`` / ``presim drive`` (default robot, one
  640x480 camera at 10 Hz, dt 0.1 s, the built-in seeded route), steps/s, new vs today.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_pointnav.py --scene out/sample --json out/bench_pointnav.json
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

TODAY = dict(lod_levels=0, reuse_move_m=0.0)


CPU_MS: list[float] = []
"""CPU ms per step of the last :func:`_steps_per_s` call is appended here (process time, all threads)."""


def _steps_per_s(step, n: int) -> float:
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        step()
    CPU_MS.append((time.process_time() - c0) * 1e3 / n)
    return n / (time.perf_counter() - t0)


def load_sim_scene(path: str | None):
    """``(folder, Scene)``: the saved scene at ``path``, or (None) the sample scene (seed 0, 30 frames
    640x480), built once into the temp directory as benchmarks/bench_sim.py does."""
    import tempfile

    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene
    from presim.capture.store import load_scene

    if path is None:
        path = str(Path(tempfile.gettempdir()) / "presim_bench_sim_sample_seed0_640x480_30")
        if not (Path(path) / "scene.json").is_file():
            build_sample_scene(path, seed=0, config=SampleSceneConfig(num_frames=30), overwrite=True)
    return path, load_scene(path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="saved scene folder with a floor (default: the sample scene, seed 0, "
                    "30 frames, built once into the temp directory as benchmarks/bench_sim.py does)")
    ap.add_argument("--steps", type=int, default=20, help="steps per measured repeat")
    ap.add_argument("--warmup-steps", type=int, default=3,
                    help="steps each env takes before the measured repeats (timed: the cold rate); "
                    "200 measures the steady state of a long run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--drive-steps", type=int, default=10)
    ap.add_argument("--vector", default="torch_batch,numba,numba-1-thread,numba-workers",
                    help="vector env renderers to measure, comma-separated, of torch_batch, numba, "
                    "numba-1-thread, numba-workers (robots split over max(2, cores) worker processes) ('' = none)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    for name in ("steps", "warmup_steps", "repeats", "num_envs", "drive_steps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if any(v and v not in ("torch_batch", "numba", "numba-1-thread", "numba-workers") for v in args.vector.split(",")):
        ap.error(f"--vector: unknown renderer in {args.vector!r} (torch_batch, numba, numba-1-thread, numba-workers)")
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    from presim.sensors.camera import CameraSpec
    from presim.sim.envs import PointNavEnv
    from presim.sim.robot import default_robot
    from presim.sim.routes import RouteDriver, ground_route
    from presim.sim.simulator import SimConfig, Simulator
    from presim.sim.vector_env import PointNavVectorEnv
    from presim.synthesis.renderer import RenderConfig, Renderer

    args.scene, scene = load_sim_scene(args.scene)
    print(f"scene {args.scene}  cpus {os.cpu_count()}  load average {os.getloadavg()}", flush=True)
    res: dict[str, dict] = {}

    # ---- single env (new, today) and vector envs: every repeat measures each of them in turn ------
    steppers: dict[str, tuple] = {}  # name -> (step function, env-steps per call)
    envs = {"new": PointNavEnv(scene),
            "today": PointNavEnv(scene, renderer=Renderer(scene, RenderConfig(**TODAY)))}
    for name, env in envs.items():
        env.reset(seed=0)
        rng = np.random.default_rng(0)

        def step(env=env, rng=rng):
            _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            if te or tr:
                env.reset()
        steppers[name] = (step, 1)
    workers = max(2, os.cpu_count() or 1)
    vector = {"torch_batch": ("torch_batch", 0, 0), "numba": ("numba", 0, 0), "numba-1-thread": ("numba", 1, 0),
              "numba-workers": ("numba", 1, workers)}
    venvs = {}
    for v in (v for v in args.vector.split(",") if v):
        backend, threads, nproc = vector[v]
        venv = PointNavVectorEnv(scene if not nproc else args.scene, num_envs=args.num_envs,
                                 render=RenderConfig(backend=backend, batch_threads=threads), workers=nproc)
        venv.reset(seed=0)
        rng = np.random.default_rng(0)

        def vstep(venv=venv, rng=rng):
            venv.step(rng.uniform(-1, 1, (args.num_envs, 2)).astype(np.float32))
        name = backend if threads != 1 else f"{backend} 1 thread"
        name = f"{backend} {nproc} workers" if nproc else name
        venvs[name] = venv
        steppers[name] = (vstep, args.num_envs)
    cold = {}
    for name, (step, per) in steppers.items():
        step()  # untimed: loads the compiled kernels
        cold[name] = _steps_per_s(step, args.warmup_steps) * per
    rates = {name: [] for name in steppers}
    cpu = {name: [] for name in steppers}
    order = list(steppers)
    for rep in range(args.repeats):
        for name in order[rep % len(order):] + order[:rep % len(order)]:  # rotated: no fixed position
            step, per = steppers[name]
            rates[name].append(_steps_per_s(step, args.steps) * per)
            cpu[name].append(CPU_MS[-1] / per)
    single = statistics.median(rates["new"])
    res["pointnav single"] = {"steps_per_s_median": single, "today_steps_per_s_median": statistics.median(rates["today"]),
                              "speedup_vs_today": single / statistics.median(rates["today"]),
                              "runs": rates["new"], "today_runs": rates["today"],
                              "cpu_ms_per_step_median": statistics.median(cpu["new"]),
                              "today_cpu_ms_per_step_median": statistics.median(cpu["today"]),
                              "warmup_steps": args.warmup_steps, "cold_steps_per_s": cold["new"],
                              "today_cold_steps_per_s": cold["today"]}
    r1 = res["pointnav single"]
    print(f"PointNav single env 128x96 : {single:7.1f} steps/s   today {statistics.median(rates['today']):7.1f}  "
          f"-> x{r1['speedup_vs_today']:.2f}   CPU ms/step {r1['cpu_ms_per_step_median']:.1f} vs today "
          f"{r1['today_cpu_ms_per_step_median']:.1f} -> x{r1['today_cpu_ms_per_step_median'] / r1['cpu_ms_per_step_median']:.2f}"
          f"   (first {args.warmup_steps} steps: {cold['new']:.1f}, today {cold['today']:.1f})", flush=True)
    for name, venv in venvs.items():
        med = statistics.median(rates[name])
        cpu_env = statistics.median(cpu[name])
        # ratio of each repeat to the single env's repeat of the same round (same load)
        pair = statistics.median(v / s for v, s in zip(rates[name], rates["new"]))
        res[f"pointnav vector {args.num_envs} {name}"] = {
            "env_steps_per_s_median": med, "ratio_vs_single": med / single, "ratio_vs_single_paired_median": pair,
            "runs": rates[name], "cpu_ms_per_env_step_median": cpu_env,
            "frame_threads": venv.renderer.batch_threads(args.num_envs) if venv.renderer is not None else 1,
            "worker_processes": venv.workers,
            "cold_env_steps_per_s": cold[name], "cold_ratio_vs_single": cold[name] / cold["new"]}
        print(f"PointNav vector env x{args.num_envs} ({name:15s}): {med:7.1f} env-steps/s  = "
              f"x{med / single:.2f} the single env (paired x{pair:.2f})   CPU ms/env-step {cpu_env:.1f}   "
              f"(first {args.warmup_steps} steps: {cold[name]:.1f} = x{cold[name] / cold['new']:.2f})", flush=True)
        venv.close()

    # ---- demo drive: 640x480 camera, built-in route -------------------------------------------
    sims = {}
    for name, rc in (("new", RenderConfig()), ("today", RenderConfig(**TODAY))):
        sim = Simulator(scene, default_robot(), SimConfig(dt_s=0.1, cameras=(CameraSpec(width=640, height=480,
                                                                                         rate_hz=10.0),), render=rc))
        sim.reset(0)
        drv = RouteDriver(ground_route(sim, np.random.default_rng(0)), sim)
        sim.step(drv.action(sim))
        sims[name] = (sim, drv)
    rates = {name: [] for name in sims}
    cpu = {name: [] for name in sims}
    for _ in range(args.repeats):
        for name, (sim, drv) in sims.items():
            rates[name].append(_steps_per_s(lambda: sim.step(drv.action(sim)), args.drive_steps))
            cpu[name].append(CPU_MS[-1])
    d_new, d_old = statistics.median(rates["new"]), statistics.median(rates["today"])
    res["demo drive 640x480"] = {"steps_per_s_median": d_new, "today_steps_per_s_median": d_old,
                                 "speedup_vs_today": d_new / d_old, "runs": rates["new"], "today_runs": rates["today"],
                                 "cpu_ms_per_step_median": statistics.median(cpu["new"]),
                                 "today_cpu_ms_per_step_median": statistics.median(cpu["today"])}
    print(f"demo drive 640x480         : {d_new:7.2f} steps/s   today {d_old:7.2f}  -> x{d_new / d_old:.2f}   "
          f"CPU ms/step {statistics.median(cpu['new']):.1f} vs today {statistics.median(cpu['today']):.1f}")
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MB (all envs of this process)  load average {os.getloadavg()}")
    if args.json:
        Path(args.json).write_text(json.dumps({"results": res, "peak_rss_mb": peak,
                                               "load_average_end": os.getloadavg()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
