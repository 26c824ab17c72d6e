"""The public Python API: open a scene, render it at any pose, drive a robot through it.

Three names, also exported lazily from ``presim`` itself (``import presim`` stays light):

- :func:`open_scene` -- a saved scene folder (``presim import`` / ``presim sample-scene``), or a
  capture folder any importer reads (imported in memory), as a :class:`Scene`.
- :class:`Scene` -- the captured scene (:class:`presim.capture.scene.Scene`, so every function that
  takes a scene takes it) plus :meth:`Scene.render`.
- :class:`Simulator` -- :class:`presim.sim.simulator.Simulator` built from a scene (or a path) and a
  robot name; ``reset(seed)`` / ``step(action)`` return a ``StepResult`` with exact ground truth.

The Gymnasium environments take the same scene: ``gymnasium.make("PreSim-PointNav-v0", scene=scene)``
(:mod:`presim.sim.envs`, which this module imports, registers the ids; a mobile base, so the scene needs a
floor). docs/api.md has the examples.

Poses are ``T_world_cam`` (camera-to-world) with the OpenCV camera frame (x right, y down, z forward),
metres; the world frame is the scene's (docs/conventions.md).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

from presim.capture.scene import Scene as _CaptureScene
from presim.geometry import Intrinsics, check_rigid, pose_from_tum
import presim.sim.envs  # noqa: F401 - registers the Gymnasium ids
from presim.align.sfm import estimate_poses
from presim.capture.open import open_scene as _open_scene
from presim.runtime import configure
from presim.sim.simulator import SimConfig
from presim.sim.simulator import Simulator as _Simulator
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.sensors.rgbd import RGBD

__all__ = ["RGBD", "RenderConfig", "Scene", "Simulator", "as_intrinsics", "as_pose", "open_scene"]


def _configure_runtime() -> None:
    """The process settings the renderer's speed depends on (presim.runtime), applied once."""
    configure()


def as_pose(pose) -> np.ndarray:
    """A camera pose as a 4x4 ``T_world_cam``: a 4x4 array, ``(xyz, quat_xyzw)`` or the 7 numbers
    ``[x, y, z, qx, qy, qz, qw]`` of a TUM line. Raises ValueError on anything else.

    Example:
        >>> as_pose(([0.1, 0.0, 0.0], [0, 0, 0, 1]))[:3, 3]
        array([0.1, 0. , 0. ])
    """
    if isinstance(pose, (tuple, list)) and len(pose) == 2:
        xyz, quat_xyzw = (np.asarray(p, dtype=np.float64).ravel() for p in pose)
        if xyz.shape != (3,) or quat_xyzw.shape != (4,):
            raise ValueError(f"pose (xyz, quat_xyzw) needs 3 + 4 numbers, got {xyz.size} + {quat_xyzw.size}")
        return pose_from_tum(np.concatenate([xyz, quat_xyzw]))
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape == (7,):
        return pose_from_tum(arr)
    if arr.shape == (4, 4):
        return check_rigid(arr, "pose T_world_cam")
    raise ValueError(f"pose must be a 4x4 T_world_cam, (xyz, quat_xyzw) or 7 numbers, got shape {arr.shape}")


def as_intrinsics(K: Intrinsics | Sequence[Intrinsics]) -> Intrinsics:
    """One :class:`~presim.geometry.Intrinsics` from ``K`` or from a scene's per-frame list
    (``scene.intrinsics``: its first frame's, as ``presim render`` uses)."""
    if isinstance(K, Intrinsics):
        return K
    if isinstance(K, (list, tuple)) and K and all(isinstance(k, Intrinsics) for k in K):
        return K[0]
    raise ValueError(f"intrinsics must be presim.geometry.Intrinsics or a list of them (scene.intrinsics), "
                     f"got {type(K).__name__}")


class Scene(_CaptureScene):
    """A captured scene that renders itself: :class:`presim.capture.scene.Scene` plus :meth:`render`.

    Build it with :func:`open_scene`. One :class:`~presim.synthesis.renderer.Renderer` per
    :class:`RenderConfig` is created on first use and kept (its view cache makes later frames faster).
    """

    def render(self, pose, size: tuple[int, int] | None = None, K: Intrinsics | Sequence[Intrinsics] | None = None,
               config: RenderConfig | None = None) -> RGBD:
        """Synthesize color + depth at camera pose ``pose``.

        Args:
            pose: 4x4 ``T_world_cam``, ``(xyz, quat_xyzw)`` or ``[x, y, z, qx, qy, qz, qw]`` (:func:`as_pose`).
            size: ``(width, height)`` of the image; the intrinsics are scaled to it (default: the scene's).
            K: intrinsics instead of the scene's: an ``Intrinsics`` or a list of them (``scene.intrinsics``);
                ``size`` rescales them too.
            config: renderer settings (default ``RenderConfig()``, as ``presim render``).

        Returns:
            :class:`~presim.sensors.rgbd.RGBD`: ``color`` uint8 (H, W, 3), ``depth_m`` float32 (H, W)
            z-depth in metres, ``valid`` bool (H, W) (False = filled hole), ``source_view`` int (H, W).
        """
        K = as_intrinsics(self.intrinsics if K is None else K)
        if size is not None:
            w, h = (int(v) for v in size)
            if w <= 0 or h <= 0:
                raise ValueError(f"size must be (width, height) > 0, got {size}")
            K = K.scaled(w, h)
        return self.renderer(config).render(as_pose(pose), K)

    def renderer(self, config: RenderConfig | None = None) -> Renderer:
        """The kept :class:`~presim.synthesis.renderer.Renderer` of ``config`` (created on first use)."""
        config = RenderConfig() if config is None else config
        cache = self.__dict__.setdefault("_renderers", {})
        if config not in cache:
            _configure_runtime()
            cache[config] = Renderer(self, config)
        return cache[config]


def open_scene(path: str | Path, poses: str = "auto", allow_capture: bool = True) -> Scene:
    """The scene at ``path``: a saved scene folder, or (``allow_capture``) a capture folder any
    importer reads, imported in memory. ``poses``: ``"auto"`` (refined by ``presim align`` when
    present), ``"given"`` or ``"refined"``. Raises :class:`presim.capture.scene.SceneError` (a
    ValueError) naming the path when nothing there can be read.

    Example:
        >>> scene = open_scene("out/apc")                         # doctest: +SKIP
        >>> scene.render(scene.T_world_cam[0], size=(160, 120)).color.shape   # doctest: +SKIP
        (120, 160, 3)
    """
    return as_scene(_open_scene(path, allow_capture=allow_capture, poses=poses, estimate_poses=estimate_poses))


def as_scene(scene: _CaptureScene | str | Path) -> Scene:
    """``scene`` as an API :class:`Scene` (a path is opened with :func:`open_scene`); shares its arrays."""
    if isinstance(scene, Scene):
        return scene
    if not isinstance(scene, _CaptureScene):
        return open_scene(scene)
    return Scene(**{f.name: getattr(scene, f.name) for f in dataclasses.fields(_CaptureScene)})


class Simulator(_Simulator):
    """:class:`presim.sim.simulator.Simulator` from a scene (or its path) and a robot name.

    Args:
        scene: an API :class:`Scene`, any ``presim.capture.scene.Scene``, or a path (:func:`open_scene`).
        robot: ``"default"`` (presim_bot, a mobile base: needs a floor), ``"free"`` (the free-flying
            camera rig), a URDF path, or None: presim_bot when the scene has a floor, else the free rig.
        size: ``(width, height)`` of the robot's RGB-D camera (intrinsics: the capture's, scaled).
        dt_s: sim time per step, seconds (the camera renders every step at ``1 / dt_s`` Hz).
        config: a full :class:`SimConfig` instead of ``size`` / ``dt_s``.

    ``reset(seed)`` and ``step(action)`` return a ``StepResult`` (``T_world_base``, ``cameras[i]``
    with ``color``, ``depth_m``, ``T_world_cam``, ...); ``action``: a base twist [vx, vy, wz]
    (the free rig: [vx, vy, vz, wx, wy, wz]) or a ``presim.sim.controllers.Action``.
    """

    def __init__(self, scene: _CaptureScene | str | Path, robot: str | Path | None = None,
                 size: tuple[int, int] = (640, 480), dt_s: float = 0.1, config: SimConfig | None = None):
        from presim.sensors.camera import CameraSpec
        from presim.sim.robot import robot_for_scene

        scene = as_scene(scene)
        if config is None:
            w, h = (int(v) for v in size)
            config = SimConfig(dt_s=dt_s, cameras=(CameraSpec(width=w, height=h, rate_hz=1.0 / dt_s),))
        _configure_runtime()
        super().__init__(scene, robot_for_scene(None if robot is None else str(robot), scene.floor is not None),
                         config)
