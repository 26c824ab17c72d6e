"""A Gymnasium vector environment of N PointNav robots whose cameras are rendered in one batch.

``PointNavVectorEnv(scene, num_envs=8)`` holds N :class:`presim.sim.envs.PointNavEnv` sharing ONE
loaded scene and ONE :class:`~presim.synthesis.renderer.Renderer` (per-view caches are shared, so
memory does not grow with N beyond the robots' occupancy maps and observations). Each step moves
all N robots (control, collision, odometry: per env, cheap), then renders the N head cameras with
one :meth:`Renderer.render_batch` call: on ``backend="torch_batch"`` (the default when CUDA is
present; pass ``render=RenderConfig(backend="torch_batch")`` to force it on CPU) that is one batch
of tensor operations; with another backend (``"numba"``, the default without CUDA) the N frames are
rendered by the per-frame core, spread over ``RenderConfig.batch_threads`` threads (auto: numba's
thread count) that run the serial, GIL-free twins of the kernels. Each env is its own camera stream
(the selection reuse of ``reuse_move_m`` applies per robot), so every env's images equal those of a
single env stepped alone.

Gymnasium 1.x vector API: ``reset(seed=..., options=...) -> (obs, infos)``,
``step(actions) -> (obs, rewards, terminations, truncations, infos)``; observations are the single
env's ``Dict(rgb, depth, goal)`` stacked along a leading axis; autoreset is ``NEXT_STEP`` (the step
after an episode ended resets that env and returns its first observation with reward 0).
``infos`` holds arrays ``success``, ``contact``, ``outside_captured_area``.

    >>> from presim.sim.vector_env import PointNavVectorEnv                      # doctest: +SKIP
    >>> venv = PointNavVectorEnv("out/sample", num_envs=8)                       # doctest: +SKIP
    >>> obs, infos = venv.reset(seed=0); obs["rgb"].shape                        # doctest: +SKIP
    (8, 96, 128, 3)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from presim.capture.scene import Scene
from presim.sim.envs import PointNavConfig, PointNavEnv, _load
from presim.sim.simulator import SIM_RENDER_CACHE_MB
from presim.synthesis.renderer import RenderConfig, Renderer

__all__ = ["default_batch_backend", "PointNavVectorEnv"]


def default_batch_backend() -> str:
    """``"torch_batch"`` when torch sees a CUDA device, else ``"numba"`` (the per-frame core, frames
    on threads: on the 2-core test machine it was faster than torch's CPU batch, see
    docs/synthesis.md)."""
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is part of the install
        return "numba"
    return "torch_batch" if torch.cuda.is_available() else "numba"


class PointNavVectorEnv(VectorEnv):
    """N point-goal navigation robots in one scene, cameras rendered in one batch (module docstring)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, scene: str | Path | Scene, num_envs: int = 8, discrete: bool = False, width: int = 128,
                 height: int = 96, config: PointNavConfig | None = None, render: RenderConfig | None = None):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        cfg = config or PointNavConfig()
        if cfg.depth_noise:
            raise ValueError("PointNavVectorEnv: depth_noise is not supported (use PointNavEnv)")
        scene_obj = _load(scene)
        rcfg = render or RenderConfig(backend=default_batch_backend(), cache_mb=SIM_RENDER_CACHE_MB)
        self.renderer = Renderer(scene_obj, rcfg)
        self.envs = [PointNavEnv(scene_obj, discrete, width, height, cfg, render_camera=False,
                                 renderer=self.renderer) for _ in range(num_envs)]
        self.num_envs = num_envs
        self.K = self.envs[0].camera_K
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._done = np.zeros(num_envs, bool)

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
        for e, s in zip(self.envs, seeds):
            e.reset(seed=s, options=options)
        self._done[:] = False
        return self._stack(self._render_all()), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if len(actions) != self.num_envs:
            raise ValueError(f"step: {len(actions)} actions for {self.num_envs} envs")
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
        for e in self.envs:
            e.close()
