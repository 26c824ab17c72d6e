"""Before/after of two source trees in one run: per-frame render and env-step cost, CPU ms medians.

Each measurement runs in a child process that imports ``presim`` from one tree (``--base``, e.g.
an exported copy of the base commit: ``git archive COMMIT | tar -x -C out/base``, or this tree);
children alternate in ABBA order (base, new, new, base, ...; ``--repeats`` pairs), so load
changes and a drifting machine speed hit both. Reported per case: median CPU ms per frame / step (process time, all threads)
and wall ms, the mean wall ms (total time / count: the throughput, which counts the steps that
stall on a view the robot meets for the first time; a median hides them), and the ratio base / new.
Cases (only APIs both trees have):

- ``render WxH``: ``Renderer(scene, RenderConfig())`` on bench_render.py's trajectory (midpoints
  of consecutive captured views), after one cold and one warm pass;
- ``pointnav``: ``PointNavEnv(scene)`` (128x96 default), random seeded actions, after ``--warm``
  steps (new views are still prepared on the way: a robot keeps discovering views);
- ``vector``: ``PointNavVectorEnv(scene, 8)`` with the numba backend, per env-step;
- ``prepare:LEVEL``: one view prepared at pyramid level LEVEL, as on a view-cache miss
  (``Renderer._build_view``: load, pool, back-project, chunk bounds), the scene's frames in turn;
- ``--base-perf`` / ``--new-perf``: ``PerfConfig`` fields for each side (e.g. the same tree with and
  without ``warp_ahead``: what a scheduling mechanism earns);
- ``drive``: the simulator with one 640x480 camera at 10 Hz and the default robot on the built-in
  seeded route (``presim demo``'s drive loop without sinks).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_ab.py --base out/base --scene /work/scenes/sample \\
        --cases render:128x128,render:256x256,pointnav,vector,drive --json out/ab.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r'''
import json, os, sys, time
sys.path.insert(0, TREE)
os.environ["PRESIM_NO_PROGRESS"] = "1"
try:  # what the CLI does first (in a tree whose import does not configure the process)
    from presim.runtime import configure
    configure()
except ImportError:
    pass
import numpy as np
import presim.runtime
getattr(presim.runtime, "configure", lambda: None)()  # trees that configure at `import presim` have none
from presim.capture.store import load_scene
scene = load_scene(SCENE)
case, n, warm = CASE, NFRAMES, WARM
cpu, wall = [], []

def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    fn()
    wall.append((time.perf_counter() - t) * 1e3)
    cpu.append((time.process_time() - c) * 1e3)

rng = np.random.default_rng(0)
PERF = PERFKW


def make_renderer(**perf):
    from presim.synthesis.renderer import RenderConfig, Renderer
    if not PERF and not perf:
        return Renderer(scene, RenderConfig())
    from presim.synthesis.renderer import PerfConfig
    return Renderer(scene, RenderConfig(), PerfConfig(**{**perf, **PERF}))


if case.startswith("render:"):
    from presim.geometry import Intrinsics
    from presim.synthesis.renderer import RenderConfig, Renderer
    w, h = (int(x) for x in case.split(":")[1].split("x"))
    K = Intrinsics.from_fov(w, h, scene.intrinsics[0].hfov_deg)
    T = scene.T_world_cam
    poses = []
    for i in range(n):
        a, b = T[i % (len(T) - 1)], T[i % (len(T) - 1) + 1]
        p = a.copy(); p[:3, 3] = (a[:3, 3] + b[:3, 3]) / 2.0; poses.append(p)
    r = make_renderer()
    for p in poses + poses:
        r.render(p, K)
    for p in poses:
        timed(lambda: r.render(p, K))
elif case.startswith("prepare:"):
    # one view prepared at a level of detail (the work of a view-cache miss), every frame in turn
    from presim.synthesis.renderer import RenderConfig, Renderer
    level = int(case.split(":")[1])
    r = Renderer(scene, RenderConfig())
    for i in range(len(scene)):
        r.grid_points(i)  # the grids are kept apart from the views: not part of a miss
    build = getattr(r, "_build_view", None) or r._prepare  # (the base tree's name)
    build(0, level)
    for k in range(n):
        timed(lambda: build(k % len(scene), level))
elif case == "pointnav":
    from presim.sim.envs import PointNavEnv
    env = PointNavEnv(scene, renderer=make_renderer(cache_mb=160.0) if PERF else None); env.reset(seed=0)
    def step():
        _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        if te or tr:
            env.reset()
    for _ in range(warm):
        step()
    for _ in range(n):
        timed(step)
elif case == "vector":
    from presim.sim.vector_env import PointNavVectorEnv
    venv = PointNavVectorEnv(scene, num_envs=8)
    venv.reset(seed=0)
    step = lambda: venv.step(rng.uniform(-1, 1, (8, 2)).astype(np.float32))
    for _ in range(max(1, warm // 8)):
        step()
    for _ in range(max(2, n // 8)):
        timed(step)
    cpu = [c / 8 for c in cpu]; wall = [x / 8 for x in wall]
elif case == "drive":
    from presim.sensors.camera import CameraSpec
    from presim.sim.robot import default_robot
    from presim.sim.routes import RouteDriver, ground_route
    from presim.sim.simulator import SimConfig, Simulator
    sim = Simulator(scene, default_robot(), SimConfig(dt_s=0.1, cameras=(CameraSpec(width=640, height=480,
                                                                                      rate_hz=10.0),)))
    sim.reset(0)
    drv = RouteDriver(ground_route(sim, np.random.default_rng(0)), sim)
    for _ in range(warm):
        sim.step(drv.action(sim))
    for _ in range(n):
        timed(lambda: sim.step(drv.action(sim)))
print(json.dumps({"cpu_ms": cpu, "wall_ms": wall}))
'''


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the baseline source tree (holds presim/)")
    ap.add_argument("--new", default=str(ROOT), help="the new source tree (default: this one)")
    ap.add_argument("--scene", required=True, help="saved scene (with a floor for the env cases)")
    ap.add_argument("--cases", default="render:128x128,render:256x256,pointnav,vector,drive")
    ap.add_argument("--n", type=int, default=20, help="measured frames / steps per child")
    ap.add_argument("--warm", type=int, default=10, help="env warm-up steps per child")
    ap.add_argument("--repeats", type=int, default=2, help="base/new pairs per case")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--base-perf", default="{}", help='PerfConfig fields of the base children, JSON, e.g. \'{"warp_ahead": false}\'')
    ap.add_argument("--new-perf", default="{}", help="PerfConfig fields of the new children, JSON")
    args = ap.parse_args()
    trees = {"base": str(Path(args.base).resolve()), "new": str(Path(args.new).resolve())}
    perfs = {"base": json.loads(args.base_perf), "new": json.loads(args.new_perf)}
    print(f"scene {args.scene}  load average at start {os.getloadavg()}", flush=True)
    res: dict[str, dict] = {}
    for case in args.cases.split(","):
        runs: dict[str, dict[str, list]] = {k: {"cpu_ms": [], "wall_ms": []} for k in trees}
        for rep in range(args.repeats):
            # ABBA order (base, new, new, base, ...): a linear drift of the machine's speed hits both
            # trees alike; with ABAB the new tree always ran one slot later (2026-12-03: two ABAB
            # runs of the same two trees with their roles swapped measured 0.92x and 1.07x).
            order = list(trees.items()) if rep % 2 == 0 else list(trees.items())[::-1]
            for name, tree in order:
                code = (CHILD.replace("TREE", repr(tree)).replace("SCENE", repr(args.scene))
                        .replace("CASE", repr(case)).replace("WARM", str(args.warm)).replace("NFRAMES", str(args.n))
                        .replace("PERFKW", repr(perfs[name])))
                env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
                p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tree)
                if p.returncode != 0:
                    raise SystemExit(f"{case} {name} failed:\n{p.stderr[-3000:]}")
                r = json.loads(p.stdout.strip().splitlines()[-1])
                for k in r:
                    runs[name][k].extend(r[k])
        med = {name: {k: statistics.median(v) for k, v in d.items()} for name, d in runs.items()}
        mean = {name: statistics.fmean(d["wall_ms"]) for name, d in runs.items()}
        for name in med:
            med[name]["mean_wall_ms"] = mean[name]
        res[case] = {"base": med["base"], "new": med["new"], "n_samples": len(runs["new"]["cpu_ms"]),
                     "mean_wall_ratio_base_over_new": mean["base"] / mean["new"],
                     "cpu_ratio_base_over_new": med["base"]["cpu_ms"] / med["new"]["cpu_ms"],
                     "load_average": os.getloadavg()}
        print(f"{case:16s} CPU ms median: base {med['base']['cpu_ms']:7.1f}  new {med['new']['cpu_ms']:7.1f}  "
              f"-> x{res[case]['cpu_ratio_base_over_new']:.2f}   wall ms: base {med['base']['wall_ms']:7.1f}  "
              f"new {med['new']['wall_ms']:7.1f}   mean wall ms: base {mean['base']:7.1f}  new {mean['new']:7.1f} "
              f"-> x{mean['base'] / mean['new']:.2f}   load {os.getloadavg()[0]:.1f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": args.scene, "trees": trees, "perf": perfs, "results": res},
                                              indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
