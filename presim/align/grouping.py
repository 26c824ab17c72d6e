"""Grouping of camera poses for local refinement (thesis §5.3.3, Fig. 5.5).

A key pose is drawn at random (seeded) from the poses not yet grouped; the other ungrouped poses are
ranked by camera-centre distance to it; those whose viewing direction differs from the key's by more
than the field of view are dropped; the key plus the nearest ``max_group - 1`` remaining ones form a
group. Repeat on what is left until every pose is in exactly one group.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GroupConfig", "PoseGroup", "group_poses", "view_angles_rad"]


@dataclass(frozen=True)
class GroupConfig:
    max_group: int = 10
    """Poses per group, key included (thesis: up to ten)."""
    fov_rad: float | None = None
    """Largest angle between viewing directions inside a group; None = the camera's horizontal FOV."""


@dataclass(frozen=True)
class PoseGroup:
    key_idx: int
    member_idxs: tuple[int, ...]
    """Other poses of the group, nearest first (key not included)."""


def view_angles_rad(T_world_cam: np.ndarray, idx: int) -> np.ndarray:
    """Angle between the optical axis (camera +z) of pose ``idx`` and of every pose, radians (N,)."""
    z = T_world_cam[:, :3, 2]
    c = np.clip(z @ z[idx], -1.0, 1.0)
    return np.arccos(c)


def group_poses(T_world_cam: np.ndarray, fov_rad: float, config: GroupConfig = GroupConfig(),
                seed: int = 0) -> list[PoseGroup]:
    """Partition poses ``(N, 4, 4)`` into groups as §5.3.3 (see module doc). Deterministic for a seed.

    Example: 12 cameras on a line 0.1 m apart, all looking along +z, ``max_group=4`` -> three groups of 4
    nearest neighbours around the drawn keys.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (N, 4, 4), got {T.shape}")
    if config.max_group < 1:
        raise ValueError(f"max_group must be >= 1, got {config.max_group}")
    fov = config.fov_rad if config.fov_rad is not None else fov_rad
    rng = np.random.default_rng(seed)
    centres = T[:, :3, 3]
    left = np.ones(len(T), dtype=bool)
    groups: list[PoseGroup] = []
    while left.any():
        cand = np.flatnonzero(left)
        key = int(cand[rng.integers(len(cand))])
        dist = np.linalg.norm(centres - centres[key], axis=1)
        ang = view_angles_rad(T, key)
        ok = left & (ang <= fov)
        ok[key] = False
        others = np.flatnonzero(ok)
        others = others[np.argsort(dist[others], kind="stable")][: config.max_group - 1]
        groups.append(PoseGroup(key, tuple(int(i) for i in others)))
        left[key] = False
        left[others] = False
    return groups
