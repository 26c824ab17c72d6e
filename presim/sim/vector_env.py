"""A Gymnasium vector environment of N PointNav robots whose cameras are rendered in one batch.

``PointNavVectorEnv(scene, num_envs=8)`` holds N :class:`presim.sim.envs.PointNavEnv` sharing ONE
loaded scene and ONE :class:`~presim.synthesis.renderer.Renderer` (per-view caches are shared, so
memory does not grow with N beyond the robots' occupancy maps and observations). Each step moves
all N robots (control, collision, odometry: per env, cheap), then renders the N head cameras with
one :meth:`Renderer.render_batch` call, one frame after another. Each env is its own camera stream
(the selection reuse of ``reuse_move_m`` applies per robot), so every env's images equal those of a
single env stepped alone.

**Worker processes** (``workers=W``, W >= 2): the N robots are split over W processes (robots
0..N/W-1 in the first, and so on), each holding its own loaded scene, renderer and per-view cache
and rendering its robots' frames one after another on one thread; the main process only sends the
actions and gathers the observations. Python's lock on the interpreter (the GIL) lets two threads
of one process render small frames only ~1.3x as fast as one (the Python between the kernels runs
one thread at a time), processes do not share it (docs/synthesis.md, "Vector env on worker
processes"). Observations, rewards and flags equal the in-process env's (same seeds per robot,
tested). The workers start with the ``spawn`` method (no fork of a process with running threads),
a few seconds each, so a script that makes one needs the usual ``if __name__ == "__main__":``
guard; ``close()`` stops them (they are daemons: they also end with the main process). Memory: one
scene and one cache per worker (``SIM_RENDER_CACHE_MB`` each by default). Pass the scene's folder:
each worker then memory-maps its pixel arrays (shared page cache); a ``Scene`` object is pickled
into every worker with its frames copied (133 MB for the 60-frame VGA sample scene).

Gymnasium 1.x vector API: ``reset(seed=..., options=...) -> (obs, infos)``,
``step(actions) -> (obs, rewards, terminations, truncations, infos)``; observations are the single
env's ``Dict(rgb, depth, goal)`` stacked along a leading axis; autoreset is ``NEXT_STEP`` (the step
after an episode ended resets that env and returns its first observation with reward 0).
``infos`` holds arrays ``success``, ``contact``, ``outside_captured_area``.

    >>> from presim.sim.vector_env import PointNavVectorEnv                      # doctest: +SKIP
    >>> venv = PointNavVectorEnv("out/sample", num_envs=8)                       # doctest: +SKIP
    >>> obs, infos = venv.reset(seed=0); obs["rgb"].shape                        # doctest: +SKIP
    (8, 96, 128, 3)
    >>> venv = PointNavVectorEnv("out/sample", num_envs=8, workers=2)            # doctest: +SKIP
"""

from __future__ import annotations

import multiprocessing
import os
import traceback
from pathlib import Path

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from presim import runtime
from presim.capture.scene import Scene
from presim.sim.envs import PointNavConfig, PointNavEnv, load_scene_arg
from presim.sim.simulator import SIM_RENDER_CACHE_MB
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

__all__ = ["PointNavVectorEnv", "WorkerError"]


class PointNavVectorEnv(VectorEnv):
    """N point-goal navigation robots in one scene, cameras rendered in one batch (module docstring)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, scene: str | Path | Scene, num_envs: int = 8, discrete: bool = False, width: int = 128,
                 height: int = 96, config: PointNavConfig | None = None, render: RenderConfig | None = None,
                 workers: int = 0, perf: PerfConfig | None = None):
        """Args (besides the single env's): ``num_envs`` robots; ``render`` / ``perf``: the shared
        renderer's configs (default: ``RenderConfig()``, the cache bounded by ``SIM_RENDER_CACHE_MB``);
        ``workers``: 0 or 1 = all robots in this process, W >= 2 = split over W worker processes
        (at most ``num_envs``; see the module doc). ``renderer`` and ``envs`` are None then."""
        runtime.configure()
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        cfg = config or PointNavConfig()
        if cfg.depth_noise:
            raise ValueError("PointNavVectorEnv: depth_noise is not supported (use PointNavEnv)")
        scene_obj = load_scene_arg(scene)  # also in the workers' case: a bad scene fails here, in this process
        rcfg = render or RenderConfig()
        pcfg = perf or PerfConfig(cache_mb=SIM_RENDER_CACHE_MB)
        self.num_envs = num_envs
        self.workers = min(workers, num_envs) if workers > 1 else 0
        self._pool: _WorkerPool | None = None
        if self.workers:
            self.renderer = None
            self.envs = None
            self._pool = _WorkerPool(scene if isinstance(scene, Scene) else str(Path(scene).resolve()), num_envs,
                                     (discrete, width, height, cfg, rcfg, pcfg), self.workers)
            self.single_observation_space, self.single_action_space, self.K = self._pool.spaces
        else:
            self.renderer = Renderer(scene_obj, rcfg, pcfg)
            self.envs = [PointNavEnv(scene_obj, discrete, width, height, cfg, render_camera=False,
                                     renderer=self.renderer) for _ in range(num_envs)]
            self.K = self.envs[0].camera_K
            self.single_observation_space = self.envs[0].observation_space
            self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._done = np.zeros(num_envs, bool)

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the worker processes (empty without workers)."""
        return [p.pid for p in self._pool.procs] if self._pool is not None else []

    def _render_all(self) -> list[dict]:
        poses = np.stack([e.camera_pose() for e in self.envs])
        frames = self.renderer.render_batch(poses, self.K)
        return [e.set_camera_images(f.color, f.depth_m) for e, f in zip(self.envs, frames)]

    @staticmethod
    def _stack(obs: list[dict]) -> dict:
        return {k: np.stack([o[k] for o in obs]) for k in obs[0]}

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"reset: {len(seeds)} seeds for {self.num_envs} envs")
        self._done[:] = False
        if self._pool is not None:
            return self._pool.reset(seeds, options), {}
        for e, s in zip(self.envs, seeds):
            e.reset(seed=s, options=options)
        return self._stack(self._render_all()), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if len(actions) != self.num_envs:
            raise ValueError(f"step: {len(actions)} actions for {self.num_envs} envs")
        if self._pool is not None:
            return self._pool.step(actions)
        n = self.num_envs
        rew = np.zeros(n, np.float64)
        term = np.zeros(n, bool)
        trunc = np.zeros(n, bool)
        info = {k: np.zeros(n, bool) for k in ("success", "contact", "outside_captured_area")}
        for i, e in enumerate(self.envs):
            if self._done[i]:
                e.reset()  # NEXT_STEP autoreset: this step only starts the new episode
                continue
            _, r, te, tr, inf = e.step(actions[i])
            rew[i], term[i], trunc[i] = r, te, tr
            for k in info:
                info[k][i] = bool(inf[k])
        self._done = term | trunc
        return self._stack(self._render_all()), rew, term, trunc, info

    def close_extras(self, **kwargs) -> None:
        if self._pool is not None:
            self._pool.close()
            return
        for e in self.envs:
            e.close()


def _worker_main(conn, scene, n: int, env_args: tuple, numba_threads: int) -> None:
    """A worker process: an in-process :class:`PointNavVectorEnv` of ``n`` robots answering the
    main process's ``("reset", (seeds, options))`` / ``("step", actions)`` / ``("close", None)``
    with ``("ok", result)`` or ``("error", traceback text)``."""
    import signal

    # Ctrl-C in a terminal reaches the whole process group: the main process handles it (and
    # closes the workers); a worker interrupted mid-step would only leave its robots half stepped.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import numba

        numba.set_num_threads(max(1, min(numba_threads, numba.config.NUMBA_NUM_THREADS)))
        venv = PointNavVectorEnv(scene, n, *env_args[:5], workers=0, perf=env_args[5])
        conn.send(("ok", (venv.single_observation_space, venv.single_action_space, venv.K)))
    except BaseException:  # noqa: BLE001 - reported to the main process, which raises it
        conn.send(("error", traceback.format_exc()))
        return
    while True:
        try:
            cmd, arg = conn.recv()
        except (EOFError, OSError):  # the main process went away
            break
        try:
            if cmd == "reset":
                out = venv.reset(seed=arg[0], options=arg[1])[0]
            elif cmd == "step":
                out = venv.step(arg)
            elif cmd == "close":
                venv.close()
                conn.send(("ok", None))
                break
            else:
                raise ValueError(f"unknown command {cmd!r}")
            conn.send(("ok", out))
        except BaseException:  # noqa: BLE001
            conn.send(("error", traceback.format_exc()))


def _joined(parts: list):
    """The workers' batches (arrays, or dicts of arrays) joined along the robot axis, in worker order."""
    if isinstance(parts[0], dict):
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return np.concatenate(parts)


class WorkerError(RuntimeError):
    """An exception inside a :class:`PointNavVectorEnv` worker process (its traceback is in the message)."""


class _WorkerPool:
    """W worker processes holding consecutive slices of the robots (see the module doc)."""

    def __init__(self, scene, num_envs: int, env_args: tuple, workers: int):
        bounds = np.linspace(0, num_envs, workers + 1).round().astype(int)
        self.slices = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        ctx = multiprocessing.get_context("spawn")
        threads = max(1, (os.cpu_count() or 1) // workers)
        self.conns, self.procs = [], []
        self.broken = False
        try:
            for a, b in self.slices:
                here, there = ctx.Pipe()
                p = ctx.Process(target=_worker_main, args=(there, scene, b - a, env_args, threads), daemon=True,
                                name=f"presim-vector-env-{a}-{b}")
                p.start()
                there.close()
                self.conns.append(here)
                self.procs.append(p)
            self.spaces = self._gather()[0]
        except BaseException:
            self.close()
            raise

    def _gather(self) -> list:
        """Every worker's answer, in order; a worker's error is raised here with its traceback."""
        out, failed = [], None
        for w, conn in enumerate(self.conns):  # every answer is read, so none is left for the next call
            try:
                status, val = conn.recv()
            except (EOFError, OSError) as e:
                self.procs[w].join(timeout=1.0)
                raise RuntimeError(f"PointNavVectorEnv worker {w} (robots {self.slices[w][0]}.."
                                   f"{self.slices[w][1] - 1}) died (exit code {self.procs[w].exitcode})") from e
            if status == "error" and failed is None:
                failed = (w, val)
            out.append(val)
        if failed is not None:
            w, tb = failed
            raise WorkerError(f"PointNavVectorEnv worker {w} (robots {self.slices[w][0]}..{self.slices[w][1] - 1}) "
                              f"failed:\n{tb}")
        return out

    def _call(self, cmd: str, args: list) -> list:
        """Send each worker its command, then gather the answers. An interruption in between (Ctrl-C)
        would leave answers in the pipes for the next call, so the pool refuses further calls."""
        if self.broken:
            raise RuntimeError("PointNavVectorEnv: a step or reset of the worker processes was interrupted; "
                               "close() this env and make a new one")
        try:
            for conn, arg in zip(self.conns, args):
                conn.send((cmd, arg))
            return self._gather()
        except WorkerError:  # the pipes are clean: the env stays usable (the other robots did step)
            raise
        except BaseException:
            self.broken = True
            raise

    def reset(self, seeds: list, options) -> dict:
        return _joined(self._call("reset", [(list(seeds[a:b]), options) for a, b in self.slices]))

    def step(self, actions: np.ndarray):
        parts = self._call("step", [actions[a:b] for a, b in self.slices])
        return tuple(_joined([p[j] for p in parts]) for j in range(5))

    def close(self) -> None:
        for conn in self.conns:
            try:
                conn.send(("close", None))
            except (OSError, ValueError):
                pass
        for conn, p in zip(self.conns, self.procs):
            try:
                if conn.poll(10.0):
                    conn.recv()
            except (EOFError, OSError):
                pass
            p.join(timeout=10.0)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5.0)
            conn.close()
        self.conns, self.procs = [], []
