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

``--bench-render=ARGS`` (with ``=``: ARGS starts with a dash) instead runs each tree's own ``benchmarks/bench_render.py ARGS --json ...``
(the speed check of two trees: each tree measured by its own script), children in the same ABBA
order, and reports per result key (``"NAME WxH"``) the median ``fps_median`` of each tree, the ratio
new / base of those medians and the median of the per-pair ratios.

    python benchmarks/bench_ab.py --base out/base --scene out/sample \\
        --cases render:128x128,render:256x256,pointnav,vector,drive --json out/ab.json
    python benchmarks/bench_ab.py --base out/base --new . --base-perf '{"warp_ahead": false}' \\
        --new-perf '{}' --scene out/apc --cases render:640x480          # what warp-ahead earns
    python benchmarks/bench_ab.py --base out/base --repeats 3 --json out/speed.json \\
        --bench-render="--scene out/apc_r --sizes 640x480,128x128 --no-today --frames 30"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402

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
    if PERF:
        from presim.sim.simulator import SIM_RENDER_CACHE_MB
        from presim.synthesis.renderer import PerfConfig
        venv = PointNavVectorEnv(scene, num_envs=8, perf=PerfConfig(**{"cache_mb": SIM_RENDER_CACHE_MB, **PERF}))
    else:
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
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=640, height=480, rate_hz=10.0),))
    if PERF:
        import dataclasses
        cfg = dataclasses.replace(cfg, perf=dataclasses.replace(cfg.perf, **PERF))
    sim = Simulator(scene, default_robot(), cfg)
    sim.reset(0)
    drv = RouteDriver(ground_route(sim, np.random.default_rng(0)), sim)
    for _ in range(warm):
        sim.step(drv.action(sim))
    for _ in range(n):
        timed(lambda: sim.step(drv.action(sim)))
print(json.dumps({"cpu_ms": cpu, "wall_ms": wall}))
'''


def _env() -> dict:
    """The children's environment: no PYTHONPATH (each child imports the presim of its own tree)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def _order(trees: dict, rep: int) -> list:
    # ABBA order (base, new, new, base, ...): a linear drift of the machine's speed hits both
    # trees alike; with ABAB the new tree always runs one slot later (two ABAB runs of the
    # same two trees with their roles swapped measured 0.92x and 1.07x).
    return list(trees.items()) if rep % 2 == 0 else list(trees.items())[::-1]


def bench_render_trees(trees: dict[str, str], script_args: str, repeats: int) -> dict:
    """Each tree's own ``benchmarks/bench_render.py SCRIPT_ARGS`` in ABBA order; per result key the
    medians of ``fps_median`` / ``cpu_ms_median`` and the ratios new / base."""
    runs: dict[str, dict[str, list]] = {name: {} for name in trees}
    for rep in range(repeats):
        for name, tree in _order(trees, rep):
            script = Path(tree) / "benchmarks" / "bench_render.py"
            if not script.is_file():
                raise SystemExit(f"{script}: not found (--{name} must be a source tree with benchmarks/)")
            with tempfile.TemporaryDirectory(prefix="bench_ab_") as d:
                out = Path(d) / "render.json"
                cmd = [sys.executable, str(script), *shlex.split(script_args), "--json", str(out)]
                p = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=tree)
                if p.returncode != 0 or not out.is_file():
                    raise SystemExit(f"bench_render.py of {name} ({tree}) failed:\n{p.stdout[-1500:]}{p.stderr[-3000:]}")
                res = json.loads(out.read_text())["results"]
            for key, v in res.items():
                runs[name].setdefault(key, []).append((v["fps_median"], v.get("cpu_ms_median", float("nan"))))
            print(f"  {name} pass {rep + 1}: " + "  ".join(f"{k} {v['fps_median']:.1f} fps" for k, v in res.items()),
                  flush=True)
    out: dict[str, dict] = {}
    for key in runs["new"]:
        if key not in runs["base"]:
            print(f"{key}: only in the new tree's results (not compared)")
            continue
        b, n = runs["base"][key], runs["new"][key]
        fb, fn = statistics.median(x[0] for x in b), statistics.median(x[0] for x in n)
        cb, cn = statistics.median(x[1] for x in b), statistics.median(x[1] for x in n)
        pairs = statistics.median(y[0] / x[0] for x, y in zip(b, n))
        out[key] = {"base_fps_median": fb, "new_fps_median": fn, "fps_ratio_new_over_base": fn / fb,
                    "fps_ratio_paired_median": pairs, "base_cpu_ms_median": cb, "new_cpu_ms_median": cn,
                    "base_runs_fps": [x[0] for x in b], "new_runs_fps": [x[0] for x in n]}
        print(f"{key:36s} fps: base {fb:7.1f}  new {fn:7.1f}  -> new/base x{fn / fb:.3f} (paired x{pairs:.3f})   "
              f"CPU ms: base {cb:.1f}  new {cn:.1f}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="the baseline source tree (holds presim/)")
    ap.add_argument("--new", default=str(ROOT), help="the new source tree (default: this one)")
    ap.add_argument("--scene", help="saved scene (with a floor for the env cases); required unless --bench-render")
    ap.add_argument("--cases", default="render:128x128,render:256x256,pointnav,vector,drive")
    ap.add_argument("--n", type=int, default=20, help="measured frames / steps per child")
    ap.add_argument("--warm", type=int, default=10, help="env warm-up steps per child")
    ap.add_argument("--repeats", type=int, default=2, help="base/new pairs per case")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--base-perf", default="{}", help='PerfConfig fields of the base children, JSON, e.g. \'{"warp_ahead": false}\'')
    ap.add_argument("--new-perf", default="{}", help="PerfConfig fields of the new children, JSON")
    ap.add_argument("--bench-render", metavar="ARGS",
                    help="run each tree's own benchmarks/bench_render.py with these arguments instead of the cases")
    args = ap.parse_args(argv)
    trees = {"base": str(Path(args.base).resolve()), "new": str(Path(args.new).resolve())}
    for name, tree in trees.items():
        if not (Path(tree) / "presim").is_dir():
            ap.error(f"--{name} {tree}: not a source tree (no presim/ folder)")
    if args.bench_render is not None:
        print(f"trees {trees}  load average at start {os.getloadavg()}", flush=True)
        res = bench_render_trees(trees, args.bench_render, args.repeats)
        common.write_json(args.json, {"trees": trees, "bench_render_args": args.bench_render, "results": res,
                                      "load_average_end": os.getloadavg()})
        return 0
    if not args.scene:
        ap.error("--scene is required (unless --bench-render)")
    perfs = {"base": json.loads(args.base_perf), "new": json.loads(args.new_perf)}
    print(f"scene {args.scene}  load average at start {os.getloadavg()}", flush=True)
    res: dict[str, dict] = {}
    for case in args.cases.split(","):
        runs: dict[str, dict[str, list]] = {k: {"cpu_ms": [], "wall_ms": []} for k in trees}
        for rep in range(args.repeats):
            for name, tree in _order(trees, rep):
                code = (CHILD.replace("TREE", repr(tree)).replace("SCENE", repr(args.scene))
                        .replace("CASE", repr(case)).replace("WARM", str(args.warm)).replace("NFRAMES", str(args.n))
                        .replace("PERFKW", repr(perfs[name])))
                p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), cwd=tree)
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
    common.write_json(args.json, {"scene": args.scene, "trees": trees, "perf": perfs, "results": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
