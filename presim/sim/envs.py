"""Gymnasium environments (thesis Sec. 4.4, visual navigation).

Registered ids (importing this module registers them, :func:`register_envs`; so does
``gym.make("presim.sim.envs:PreSim-PointNav-v0", ...)``, which imports it first):

- ``PreSim-PointNav-v0``: continuous actions ``Box([-1, -1], [1, 1])`` = (forward speed, turn rate)
  as fractions of the base's limits;
- ``PreSim-PointNavDiscrete-v0``: ``Discrete(4)`` = 0 stop, 1 forward, 2 turn left, 3 turn right.

Observation ``Dict(rgb uint8 (H, W, 3), depth float32 (H, W, 1) metres in [0, max_depth_m],
goal float32 (2,) = [distance m, heading rad in the base frame])``. Reward per step:
``progress_m * progress_weight - collision_penalty * contact - time_penalty`` plus ``success_reward``
when the base gets within ``success_radius_m`` of the goal (episode terminates). Episodes are
truncated after ``max_episode_steps``. Goals are drawn from the seed among free cells reachable
from the start (same connected component of the map), ``min/max_goal_dist_m`` away (straight line).

Example:
    >>> import gymnasium as gym, presim.sim.envs                             # doctest: +SKIP
    >>> env = gym.make("PreSim-PointNav-v0", scene="out/sample", width=64, height=48)   # doctest: +SKIP
    >>> env = gym.make("presim.sim.envs:PreSim-PointNav-v0", scene="out/sample")  # no import needed  # doctest: +SKIP
    >>> obs, info = env.reset(seed=0)                                         # doctest: +SKIP
    >>> venv = gym.make_vec("PreSim-PointNav-v0", num_envs=8, scene="out/sample", workers=2)  # doctest: +SKIP

``gym.make_vec`` on these ids makes :class:`presim.sim.vector_env.PointNavVectorEnv` (their vector
entry point: robots rendered in batches, optionally on worker processes); pass
``vectorization_mode="sync"`` or ``"async"`` for gymnasium's wrappers of N single envs.

Constructing an env calls :func:`presim.runtime.configure` (the process settings the renderer's
speed depends on).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.ndimage import label

from presim import runtime
from presim.capture.scene import Scene
from presim.capture.store import load_scene
from presim.geometry import compose
from presim.limits import check_intrinsics, check_render_memory
from presim.sensors.camera import CameraSpec
from presim.sensors.noise import DepthNoiseConfig
from presim.sim.controllers import wrap_angle
from presim.sim.robot import default_robot
from presim.sim.simulator import SimConfig, Simulator

__all__ = ["PointNavConfig", "PointNavEnv", "register_envs"]


@dataclass(frozen=True)
class PointNavConfig:
    """Point-goal navigation task."""

    dt_s: float = 0.25
    """Sim time per env step (one camera reading per step), seconds."""
    max_episode_steps: int = 200
    """Truncation limit."""
    success_radius_m: float = 0.3
    """Success when the base centre is this close to the goal."""
    min_goal_dist_m: float = 1.0
    """Goals are at least this far from the start (straight line) when possible."""
    max_goal_dist_m: float = 4.0
    """... and at most this far."""
    progress_weight: float = 1.0
    """Reward per metre of progress towards the goal."""
    collision_penalty: float = 0.1
    """Subtracted on steps with contact."""
    time_penalty: float = 0.01
    """Subtracted every step."""
    success_reward: float = 2.5
    """Added on success."""
    max_depth_m: float = 10.0
    """Depth observations are clipped to [0, max_depth_m]."""
    hfov_deg: float = 70.0
    """Camera field of view."""
    depth_noise: bool = False
    """Apply the default seeded depth noise model."""


def load_scene_arg(scene: str | Path | Scene) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


class PointNavEnv(gym.Env):
    """Point-goal navigation with the default robot in a captured scene (see module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, scene: str | Path | Scene, discrete: bool = False, width: int = 128, height: int = 96,
                 config: PointNavConfig | None = None, render_mode: str | None = None,
                 render_camera: bool = True, renderer=None):
        runtime.configure()
        self.cfg = config or PointNavConfig()
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        check_intrinsics(width, height, prefix="")
        check_render_memory(width, height, what="one observation", size_flag="width/height")
        cam = CameraSpec(name="head_camera", width=width, height=height, hfov_deg=self.cfg.hfov_deg,
                         rate_hz=1.0 / self.cfg.dt_s, noise=DepthNoiseConfig() if self.cfg.depth_noise else None)
        # render_camera=False: the simulator renders nothing; images come from outside through
        # set_camera_images() (the vector env renders all its envs in one batch).
        scene_obj = load_scene_arg(scene)
        self.camera_K = cam.intrinsics(scene_obj.intrinsics[0])
        self.sim = Simulator(scene_obj, default_robot(), SimConfig(dt_s=self.cfg.dt_s, cameras=(cam,) if render_camera else ()),
                             renderer=renderer)
        self.discrete = discrete
        self.action_space = spaces.Discrete(4) if discrete else spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = spaces.Dict({
            "rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
            "depth": spaces.Box(0.0, self.cfg.max_depth_m, (height, width, 1), np.float32),
            "goal": spaces.Box(np.array([0.0, -np.pi], np.float32), np.array([1e3, np.pi], np.float32), (2,), np.float32),
        })
        occ = self.sim.occupancy
        free = occ.free_mask(0.05, include_unknown=True)
        self._labels, _ = label(free, structure=np.ones((3, 3)))
        self._labels[~occ.known] = 0  # goals only on known floor
        self._goal = np.zeros(2)
        self._last_rgb = np.zeros((height, width, 3), np.uint8)
        self._last_depth = np.zeros((height, width, 1), np.float32)
        self._steps = 0

    # ---- helpers -------------------------------------------------------------------------------
    def _goal_vector(self) -> np.ndarray:
        dx, dy = self._goal - (self.sim.x, self.sim.y)
        dist = float(np.hypot(dx, dy))
        heading = float(wrap_angle(np.arctan2(dy, dx) - self.sim.yaw))
        return np.array([dist, heading], np.float32)

    def _obs(self, result) -> dict:
        if result.cameras:
            c = result.cameras[0]
            self._last_rgb = c.color
            self._last_depth = np.clip(c.depth_m, 0.0, self.cfg.max_depth_m)[..., None].astype(np.float32)
        return {"rgb": self._last_rgb, "depth": self._last_depth, "goal": self._goal_vector()}

    def _sample_goal(self) -> np.ndarray:
        occ = self.sim.occupancy
        i, j = occ.cell_of(self.sim.x, self.sim.y)
        H, W = self._labels.shape
        comp = self._labels[i, j] if (0 <= i < H and 0 <= j < W) else 0
        mask = self._labels == comp if comp else self._labels > 0
        ii, jj = np.nonzero(mask)
        xy = np.stack([occ.origin_xy[0] + (jj + 0.5) * occ.resolution_m,
                       occ.origin_xy[1] + (ii + 0.5) * occ.resolution_m], axis=1)
        d = np.hypot(xy[:, 0] - self.sim.x, xy[:, 1] - self.sim.y)
        ok = (d >= self.cfg.min_goal_dist_m) & (d <= self.cfg.max_goal_dist_m)
        cand = xy[ok] if ok.any() else xy[np.argsort(d)[-max(1, len(d) // 10):]]
        return cand[int(self.np_random.integers(len(cand)))]

    def camera_pose(self) -> np.ndarray:
        """4x4 ``T_world_cam`` of the head camera now (what the observation would be rendered at)."""
        return compose(self.sim.T_world_base, self.sim.T_base_cam(0))

    def set_camera_images(self, color: np.ndarray, depth_m: np.ndarray) -> dict:
        """Use an image rendered outside (``render_camera=False``) as the current observation."""
        self._last_rgb = color
        self._last_depth = np.clip(depth_m, 0.0, self.cfg.max_depth_m)[..., None].astype(np.float32)
        return {"rgb": self._last_rgb, "depth": self._last_depth, "goal": self._goal_vector()}

    # ---- gymnasium API -------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        sim_seed = int(self.np_random.integers(0, 2**31 - 1))
        result = self.sim.reset(sim_seed)
        self._goal = self._sample_goal()
        self._steps = 0
        obs = self._obs(result)
        self._prev_dist = float(obs["goal"][0])
        return obs, {"T_world_base": result.T_world_base, "goal_xy": self._goal.copy()}

    def step(self, action):
        lim = self.sim.config.limits
        if self.discrete:
            a = int(action)
            if not 0 <= a < 4:
                raise ValueError(f"discrete action must be 0..3, got {action!r}")
            twist = [np.zeros(3), np.array([lim.max_vx_mps, 0, 0]), np.array([0, 0, lim.max_wz_radps]),
                     np.array([0, 0, -lim.max_wz_radps])][a]
        else:
            a = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -1.0, 1.0)
            twist = np.array([a[0] * lim.max_vx_mps, 0.0, a[1] * lim.max_wz_radps])
        result = self.sim.step(twist)
        self._steps += 1
        obs = self._obs(result)
        dist = float(obs["goal"][0])
        c = self.cfg
        reward = (self._prev_dist - dist) * c.progress_weight - c.time_penalty - (c.collision_penalty if result.contact else 0.0)
        self._prev_dist = dist
        success = dist < c.success_radius_m
        if success:
            reward += c.success_reward
        truncated = (not success) and self._steps >= c.max_episode_steps
        info = {"contact": result.contact, "success": success, "outside_captured_area": result.outside_captured_area,
                "T_world_base": result.T_world_base}
        return obs, float(reward), bool(success), bool(truncated), info

    def render(self):
        if self.render_mode == "rgb_array":
            return self._last_rgb.copy()
        return None

    def close(self):
        self.sim.close()


GYM_ENV_IDS = (("PreSim-PointNav-v0", False), ("PreSim-PointNavDiscrete-v0", True))
"""``(id, discrete)`` of the registered environments."""


def register_envs() -> None:
    """Register the PreSim environments with gymnasium (idempotent; importing this module does it).

    ``gym.make_vec(id, num_envs=N, scene=..., [workers=W])`` makes the batched
    :class:`~presim.sim.vector_env.PointNavVectorEnv` (``vectorization_mode="sync"`` / ``"async"``:
    gymnasium's wrappers of N single envs)."""
    for env_id, discrete in GYM_ENV_IDS:
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="presim.sim.envs:PointNavEnv", kwargs={"discrete": discrete},
                         vector_entry_point="presim.sim.vector_env:PointNavVectorEnv")


register_envs()
