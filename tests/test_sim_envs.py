"""Gymnasium: registered point-goal navigation envs pass the env checker; vector envs work."""

from __future__ import annotations

import os
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import presim.sim.envs  # noqa: F401  (registers the envs)
from presim.capture.store import save_scene
from presim.sim.envs import PointNavConfig, PointNavEnv
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    return str(save_scene(build_toy_room(ToyRoomConfig(width=80, height=48)), tmp_path_factory.mktemp("toy") / "toy"))


@pytest.mark.parametrize("env_id", ["PreSim-PointNav-v0", "PreSim-PointNavDiscrete-v0"])
def test_env_checker(env_id, toy_path):
    env = gym.make(env_id, scene=toy_path, width=64, height=48)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    assert obs["rgb"].shape == (48, 64, 3) and obs["depth"].shape == (48, 64, 1)
    assert env.observation_space.contains(obs)
    env.close()


def test_reward_progress_collision_success(toy_path):
    cfg = PointNavConfig(max_episode_steps=400, success_radius_m=0.3)
    env = PointNavEnv(toy_path, discrete=True, width=16, height=12, config=cfg)
    obs, info = env.reset(seed=3)
    # Steer with the goal vector: turn towards the goal, then drive forward.
    total, done, steps = 0.0, False, 0
    while not done:
        dist, heading = obs["goal"]
        a = 1 if abs(heading) < 0.3 else (2 if heading > 0 else 3)
        obs2, r, term, trunc, info = env.step(a)
        if a == 1 and not info["contact"]:
            assert r == pytest.approx(obs["goal"][0] - obs2["goal"][0] - cfg.time_penalty
                                      + (cfg.success_reward if term else 0.0), abs=1e-5)
        obs, total, done, steps = obs2, total + r, term or trunc, steps + 1
    assert term and info["success"] and obs["goal"][0] < cfg.success_radius_m
    # Collision penalty: drive into the pillar / wall until contact.
    env.reset(seed=3)
    env.sim.reset(0, start=np.array([3.0, 2.0, 0.0]))
    env._prev_dist = float(env._goal_vector()[0])
    rs = [env.step(1) for _ in range(12)]
    hit = [r for r in rs if r[4]["contact"]]
    assert hit and all(r[1] <= -cfg.collision_penalty - cfg.time_penalty + 1e-3 for r in hit)
    env.close()


def test_episode_truncation(toy_path):
    env = PointNavEnv(toy_path, discrete=True, width=16, height=12, config=PointNavConfig(max_episode_steps=3))
    env.reset(seed=0)
    flags = [env.step(0)[3] for _ in range(3)]
    assert flags == [False, False, True]


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_vector_envs(kind, toy_path):
    # "module:id" makes each (spawned) worker import the module that registers the env.
    fns = [lambda: gym.make("presim.sim.envs:PreSim-PointNav-v0", scene=toy_path, width=64, height=48)
           for _ in range(2)]
    # Async workers are spawned, not forked: numba's worker threads (used by the renderer) do not
    # survive a fork of a process that already ran parallel code.
    venv = gym.vector.SyncVectorEnv(fns) if kind == "sync" else gym.vector.AsyncVectorEnv(fns, context="spawn")
    try:
        obs, info = venv.reset(seed=[1, 2])
        assert obs["rgb"].shape == (2, 48, 64, 3) and obs["goal"].shape == (2, 2)
        for _ in range(3):
            obs, rew, term, trunc, info = venv.step(venv.action_space.sample())
        assert rew.shape == (2,) and obs["depth"].dtype == np.float32
        assert not np.array_equal(obs["goal"][0], obs["goal"][1])
    finally:
        venv.close()


def test_make_vec_gives_the_batched_vector_env(toy_path):
    """``gym.make_vec`` on a PreSim id makes :class:`PointNavVectorEnv` (its vector entry point);
    ``vectorization_mode="sync"`` still gives gymnasium's SyncVectorEnv of single envs."""
    from presim.sim.vector_env import PointNavVectorEnv

    venv = gym.make_vec("PreSim-PointNavDiscrete-v0", num_envs=2, scene=toy_path, width=32, height=24)
    try:
        assert isinstance(venv.unwrapped, PointNavVectorEnv) and venv.unwrapped.workers == 0
        obs, _ = venv.reset(seed=3)
        assert obs["rgb"].shape == (2, 24, 32, 3) and venv.action_space.shape == (2,)
        obs, rew, *_ = venv.step(np.array([1, 2]))
        assert rew.shape == (2,) and venv.observation_space.contains(obs)
    finally:
        venv.close()
    sync = gym.make_vec("PreSim-PointNav-v0", num_envs=2, vectorization_mode="sync", scene=toy_path, width=32,
                        height=24)
    try:
        assert isinstance(sync, gym.vector.SyncVectorEnv)
        assert sync.reset(seed=1)[0]["depth"].shape == (2, 24, 32, 1)
    finally:
        sync.close()
