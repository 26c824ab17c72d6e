"""Camera poses around a target object (thesis §5.3.6).

Seeds are captured views that see the target (the thesis drives a robot to such poses and records
them; a captured view is the same thing without the robot). Each new pose moves a seed camera along
its own axes: a random rotation of at most ``max_rotation_deg`` (yaw/pitch emphasised, roll limited
to ``max_roll_deg``) and a random translation of at most ``max_translation_m``. Candidates that lose
the target (too little of its silhouette inside the image), come too close to it, go under the floor
or into scene geometry are rejected by the caller's checks (:func:`check_candidate`); frames whose
synthesized image hides the target are dropped after annotation.

Everything is a pure function of a ``numpy.random.Generator``: seeding it with
``(seed, frame_slot, attempt)`` makes every frame reproducible on any worker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.capture.scene import Scene
from presim.datasets.objects import ObjectModel
from presim.geometry import Intrinsics, compose, invert, make_pose, project, rotation_angle_rad, transform_points

__all__ = ["CameraSamplingConfig", "seed_views", "perturb_pose", "check_candidate", "frame_rng",
           "output_intrinsics"]


@dataclass(frozen=True)
class CameraSamplingConfig:
    """Random camera poses around seed views (defaults = thesis §5.3.6)."""

    max_rotation_deg: float = 30.0
    """Largest rotation of a new camera relative to its seed view (thesis: < 30 deg)."""
    max_translation_m: float = 0.2
    """Largest displacement of the camera centre from the seed (thesis: < 0.2 m)."""
    max_roll_deg: float = 5.0
    """Largest rotation about the optical axis (roll matters little for 6D pose, thesis §5.3.6)."""
    min_in_view_fract: float = 0.5
    """Fraction of the target's silhouette that must fall inside the image (truncation check)."""
    min_target_px: int = 64
    """Smallest target silhouette inside the image, pixels."""
    min_clearance_m: float = 0.1
    """Smallest distance from the camera centre to the target's bounding sphere and to the scene's
    point cloud (the camera must not sit inside furniture)."""
    min_height_m: float = 0.05
    """Smallest camera height above the floor, when the scene has one."""
    seed_min_in_view_fract: float = 0.8
    """A captured view is a seed when this fraction of the target's bounding sphere projects into it."""


def frame_rng(seed: int, slot: int, attempt: int) -> np.random.Generator:
    """The generator of one attempt of one frame slot (independent of workers and order)."""
    return np.random.default_rng([int(seed), int(slot), int(attempt)])


def seed_views(scene: Scene, model: ObjectModel, T_world_obj: np.ndarray,
               config: CameraSamplingConfig = CameraSamplingConfig()) -> np.ndarray:
    """Indices of captured views that see the target: its bounding-sphere centre is in front of the
    camera, projects inside the image with a margin (so that ``seed_min_in_view_fract`` of the sphere
    is in view), and the captured depth there does not put a surface far in front of it.

    Returns int64 (S,) frame indices (possibly empty).
    """
    c_world = transform_points(T_world_obj, model.center_m[None])[0]
    r = model.radius_m
    out = []
    for i in range(len(scene)):
        K = scene.intrinsics[i]
        c_cam = transform_points(invert(scene.T_world_cam[i]), c_world[None])[0]
        z = c_cam[2]
        if z <= r + 1e-3:
            continue
        u, v = project(K, c_cam)[0]
        # Pixel radius of the sphere; allow (1 - fract) of it to stick out.
        rad_px = K.fx * r / z
        m = (2.0 * config.seed_min_in_view_fract - 1.0) * rad_px
        if not (m - 0.5 <= u <= K.width - 0.5 - m and m - 0.5 <= v <= K.height - 0.5 - m):
            continue
        depth = scene.depth(i, refined=True)
        ui, vi = int(round(u)), int(round(v))
        d = float(depth[min(max(vi, 0), K.height - 1), min(max(ui, 0), K.width - 1)])
        if d > 0 and d < z - 2.0 * r:  # something well in front of the whole object: occluded
            continue
        out.append(i)
    return np.asarray(out, dtype=np.int64)


def perturb_pose(rng: np.random.Generator, T_world_seed: np.ndarray,
                 config: CameraSamplingConfig = CameraSamplingConfig()) -> np.ndarray:
    """A random camera pose near ``T_world_seed``: rotation about an axis in the image plane
    (yaw/pitch) by at most ``max_rotation_deg``, a roll of at most ``max_roll_deg``, their
    composition never exceeding ``max_rotation_deg``; translation uniform in a ball of radius
    ``max_translation_m`` along the camera's axes. Returns 4x4 ``T_world_cam``."""
    max_rot = np.radians(config.max_rotation_deg)
    max_roll = np.radians(min(config.max_roll_deg, config.max_rotation_deg))
    for _ in range(100):
        phi = rng.uniform(0.0, 2.0 * np.pi)
        axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        ang = rng.uniform(0.0, max_rot)
        roll = rng.uniform(-max_roll, max_roll)
        R = _axis_angle(axis, ang) @ _axis_angle(np.array([0.0, 0.0, 1.0]), roll)
        if rotation_angle_rad(R) <= max_rot + 1e-12:
            break
    # Uniform in the ball: direction uniform on the sphere, radius ~ r_max * U^(1/3).
    d = rng.normal(size=3)
    d /= max(np.linalg.norm(d), 1e-12)
    t = d * config.max_translation_m * rng.uniform() ** (1.0 / 3.0)
    return compose(np.asarray(T_world_seed, dtype=np.float64), make_pose(R, t))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * (Kx @ Kx)


def check_candidate(T_world_cam: np.ndarray, target_px_in_image: int, target_px_all: int,
                    target_center_world: np.ndarray, target_radius_m: float, scene: Scene,
                    scene_tree, config: CameraSamplingConfig = CameraSamplingConfig()) -> str | None:
    """Why a candidate pose is rejected (a short reason used as a report counter), None if it is fine.

    ``target_px_*`` come from rendering the target model alone at the candidate pose;
    ``scene_tree`` is a ``scipy.spatial.cKDTree`` of the scene's point cloud (or None).
    """
    c = np.asarray(T_world_cam)[:3, 3]
    if np.linalg.norm(c - target_center_world) < target_radius_m + config.min_clearance_m:
        return "too_close"
    if scene.floor is not None and float(scene.floor.height_of(c)) < config.min_height_m:
        return "below_floor"
    if scene_tree is not None and config.min_clearance_m > 0:
        dist, _ = scene_tree.query(c, k=1)
        if dist < config.min_clearance_m:
            return "inside_geometry"
    if target_px_all <= 0 or target_px_in_image < config.min_target_px:
        return "target_out_of_view"
    if target_px_in_image / target_px_all < config.min_in_view_fract:
        return "target_truncated"
    return None


def output_intrinsics(K_scene: Intrinsics, width: int, height: int, hfov_deg: float | None = None) -> Intrinsics:
    """Intrinsics of generated images: square pixels, principal point at the centre, the scene's
    horizontal field of view unless ``hfov_deg`` is given (1280x720 from a 640x480 capture keeps
    the width's view and crops the height)."""
    if hfov_deg is None:
        hfov_deg = K_scene.hfov_deg
    return Intrinsics.from_fov(width, height, hfov_deg)
