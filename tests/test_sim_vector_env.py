"""PointNavVectorEnv: N robots stepped together, their cameras rendered in one batch."""

from __future__ import annotations

import os

import numpy as np
import pytest

from presim.capture.store import load_scene, save_scene
from presim.sim.envs import PointNavEnv
from presim.sim.vector_env import PointNavVectorEnv
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    return str(save_scene(build_toy_room(ToyRoomConfig(width=80, height=48)), tmp_path_factory.mktemp("toy") / "toy"))


def test_vector_env_matches_single_envs_with_the_per_frame_renderer(toy_path):
    """With the numba backend render_batch renders frame by frame: every env's observation,
    reward and flags equal a single PointNavEnv stepped with the same seed and actions."""
    venv = PointNavVectorEnv(toy_path, num_envs=2, discrete=True, width=32, height=24,
                             render=RenderConfig(reuse_move_m=0.0))
    singles = [PointNavEnv(toy_path, discrete=True, width=32, height=24) for _ in range(2)]
    obs, _ = venv.reset(seed=5)
    assert venv.observation_space.contains(obs) and obs["rgb"].shape == (2, 24, 32, 3)
    s_obs = [e.reset(seed=5 + i)[0] for i, e in enumerate(singles)]
    for i in range(2):
        for k in ("rgb", "depth", "goal"):
            np.testing.assert_array_equal(obs[k][i], s_obs[i][k])
    for t in range(3):
        acts = np.array([1, 2]) if t % 2 == 0 else np.array([3, 1])
        obs, rew, term, trunc, info = venv.step(acts)
        for i, e in enumerate(singles):
            o, r, te, tr, inf = e.step(int(acts[i]))
            np.testing.assert_array_equal(obs["rgb"][i], o["rgb"])
            np.testing.assert_array_equal(obs["depth"][i], o["depth"])
            assert rew[i] == pytest.approx(r) and term[i] == te and trunc[i] == tr
            assert info["contact"][i] == inf["contact"]
    venv.close()
    for e in singles:
        e.close()


def test_vector_env_with_temporal_reuse_matches_single_envs(toy_path):
    """The selection reuse on (each env is its own camera stream of render_batch): observations
    equal single envs stepped alone, step after step, also while the robots turn in place (moves
    small enough for the reuse)."""
    cfg = RenderConfig(reuse_move_m=0.05, reuse_turn_deg=20.0)
    venv = PointNavVectorEnv(toy_path, num_envs=3, discrete=True, width=32, height=24, render=cfg)
    scene = load_scene(toy_path)
    singles = [PointNavEnv(scene, discrete=True, width=32, height=24, renderer=Renderer(scene, cfg)) for _ in range(3)]
    venv.reset(seed=11)
    for i, e in enumerate(singles):
        e.reset(seed=11 + i)
    reused = 0
    for t in range(6):
        acts = np.array([(t + i) % 3 + 1 for i in range(3)])  # forward / turns
        obs, *_ = venv.step(acts)
        reused += venv.renderer.last.reused_selection
        for i, e in enumerate(singles):
            o, *_ = e.step(int(acts[i]))
            np.testing.assert_array_equal(obs["rgb"][i], o["rgb"])
            np.testing.assert_array_equal(obs["depth"][i], o["depth"])
    assert reused > 0  # the per-stream reuse was exercised
    venv.close()
    for e in singles:
        e.close()


def test_vector_env_torch_backend_and_autoreset(toy_path):
    from presim.sim.envs import PointNavConfig

    venv = PointNavVectorEnv(toy_path, num_envs=3, width=32, height=24,
                             config=PointNavConfig(max_episode_steps=2), perf=PerfConfig(backend="torch"))
    assert venv.renderer.perf.backend == "torch"
    obs, _ = venv.reset(seed=0)
    assert obs["rgb"].shape == (3, 24, 32, 3) and obs["depth"].shape == (3, 24, 32, 1)
    assert (obs["depth"] > 0).mean() > 0.5  # rendered, not the zero placeholder
    a = np.zeros((3, 2), np.float32)
    venv.step(a)
    _, rew, term, trunc, _ = venv.step(a)
    assert trunc.all()  # max_episode_steps = 2
    obs, rew, term, trunc, _ = venv.step(a)  # NEXT_STEP autoreset: reset, reward 0
    assert not trunc.any() and (rew == 0).all() and venv.observation_space.contains(obs)
    with pytest.raises(ValueError, match="actions"):
        venv.step(np.zeros((2, 2), np.float32))
    venv.close()


def test_vector_env_on_worker_processes_matches_the_in_process_env(toy_path):
    """``workers=2``: the robots split over two spawned processes (2 + 1) give the in-process
    env's observations, rewards, flags and infos, through an autoreset; a worker's error reaches
    the caller with its traceback; close() ends the processes."""
    from presim.sim.envs import PointNavConfig

    kw = dict(num_envs=3, discrete=True, width=32, height=24, config=PointNavConfig(max_episode_steps=3))
    local = PointNavVectorEnv(toy_path, **kw)
    venv = PointNavVectorEnv(toy_path, workers=2, **kw)
    try:
        assert venv.workers == 2 and venv.renderer is None and venv._pool.slices == [(0, 2), (2, 3)]
        assert venv.single_observation_space == local.single_observation_space
        obs, _ = venv.reset(seed=7)
        ref, _ = local.reset(seed=7)
        for k in ref:
            np.testing.assert_array_equal(obs[k], ref[k])
        for t in range(5):  # the 4th step autoresets every robot (max_episode_steps = 3)
            acts = np.array([(t + i) % 3 + 1 for i in range(3)])
            got, want = venv.step(acts), local.step(acts)
            for k in want[0]:
                np.testing.assert_array_equal(got[0][k], want[0][k])
            for j in (1, 2, 3):
                np.testing.assert_array_equal(got[j], want[j])
            for k in want[4]:
                np.testing.assert_array_equal(got[4][k], want[4][k])
        assert venv.observation_space.contains(got[0])
        with pytest.raises(RuntimeError, match=r"worker 1 \(robots 2..2\) failed:(.|\n)*discrete action must be 0..3"):
            venv.step(np.array([1, 1, 7]))
        # every worker's answer was read: the env stays usable and in step (no answer left over)
        got, want = venv.reset(seed=9)[0], local.reset(seed=9)[0]
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])
        got, want = venv.step(np.array([2, 3, 1])), local.step(np.array([2, 3, 1]))
        np.testing.assert_array_equal(got[0]["rgb"], want[0]["rgb"])
        np.testing.assert_array_equal(got[1], want[1])
        # interrupted between sending and gathering (Ctrl-C): answers may be left in the pipes, so
        # the env refuses to go on instead of handing out a previous step's observations
        pool = venv._pool
        gather = pool._gather

        def interrupted():
            raise KeyboardInterrupt
        pool._gather = interrupted
        with pytest.raises(KeyboardInterrupt):
            venv.step(np.array([1, 1, 1]))
        pool._gather = gather
        with pytest.raises(RuntimeError, match="interrupted"):
            venv.step(np.array([1, 1, 1]))
        procs = list(pool.procs)
    finally:
        venv.close()
        local.close()
    assert procs and not any(p.is_alive() for p in procs)
    with pytest.raises(ValueError, match="workers"):
        PointNavVectorEnv(toy_path, num_envs=2, workers=-1)
