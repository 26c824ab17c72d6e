"""Capture/test split, distance bins and the synthesized-view poses of the sim2real experiment.

Capture = every N-th frame of the scene (positions 0, N, 2N, ...); test = all other frames. Each test
frame is measured against its nearest capture frame by ``d = t / 0.10 m + r / 10 deg`` (t: distance
of the camera centres, r: angle of the relative rotation), so 10 cm of translation counts as much as
10 degrees of rotation. Test frames are reported in three bins by that distance: ``near`` / ``mid`` /
``far`` = the nearest, middle and farthest third of the test frames (terciles of d, so each bin has
a third of the frames; the thresholds are reported). The binning only groups the reported metrics:
it never feeds training, the renderer or any statistic a model or calibration sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["BINS", "CaptureSplit", "SynthPoseConfig", "pose_distance", "split_capture", "synth_poses"]

BINS = ("near", "mid", "far")
TRANS_UNIT_M = 0.10
"""Translation that counts as one unit of the combined pose distance."""
ROT_UNIT_DEG = 10.0
"""Rotation that counts as one unit of the combined pose distance."""


def pose_distance(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise (translation m, rotation deg) between poses ``T_a`` (A, 4, 4) and ``T_b`` (B, 4, 4),
    each an (A, B) array."""
    T_a, T_b = np.asarray(T_a, np.float64), np.asarray(T_b, np.float64)
    t = np.linalg.norm(T_a[:, None, :3, 3] - T_b[None, :, :3, 3], axis=-1)
    # angle of R_a^T R_b: trace = sum_ij Ra_ij Rb_ij
    tr = np.einsum("aij,bij->ab", T_a[:, :3, :3], T_b[:, :3, :3])
    r = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
    return t, r


@dataclass(frozen=True)
class CaptureSplit:
    """Which frames are the capture and which are real test frames, and how far each test frame is
    from the capture."""

    capture_idx: np.ndarray
    """(C,) scene positions of the capture frames (every N-th)."""
    test_idx: np.ndarray
    """(T,) scene positions of the test frames (all others)."""
    nearest_capture: np.ndarray
    """(T,) scene position of each test frame's nearest capture frame (combined distance)."""
    trans_m: np.ndarray
    """(T,) camera-centre distance to that capture frame, metres."""
    rot_deg: np.ndarray
    """(T,) rotation angle to that capture frame, degrees."""
    dist: np.ndarray
    """(T,) combined distance t / 0.10 m + r / 10 deg."""
    bin_of: np.ndarray
    """(T,) bin index into :data:`BINS` (0 near, 1 mid, 2 far)."""
    bin_edges: tuple[float, float]
    """Combined-distance thresholds between near/mid and mid/far (terciles)."""

    def bin_summary(self) -> dict:
        """Per bin: frame count, combined-distance range, median translation (m) and rotation (deg)."""
        out = {}
        for b, name in enumerate(BINS):
            m = self.bin_of == b
            out[name] = {
                "n_frames": int(m.sum()),
                "dist_min": float(self.dist[m].min()), "dist_max": float(self.dist[m].max()),
                "trans_m_median": float(np.median(self.trans_m[m])),
                "rot_deg_median": float(np.median(self.rot_deg[m])),
                "trans_m_max": float(self.trans_m[m].max()), "rot_deg_max": float(self.rot_deg[m].max()),
            }
        return out


def split_capture(T_world_cam: np.ndarray, capture_every: int) -> CaptureSplit:
    """Split a sequence of poses (N, 4, 4) into capture = every ``capture_every``-th frame and test =
    the others, with each test frame's distance to its nearest capture frame and its bin.

    Raises ValueError when the split leaves fewer than 2 capture frames or fewer than 3 test frames
    (one per bin)."""
    n = len(T_world_cam)
    if capture_every < 2:
        raise ValueError(f"--capture-every must be >= 2 (1 leaves no test frames), got {capture_every}")
    cap = np.arange(0, n, capture_every)
    test = np.setdiff1d(np.arange(n), cap)
    if len(cap) < 2:
        raise ValueError(f"--capture-every {capture_every} leaves {len(cap)} capture frame of the scene's "
                         f"{n}; need >= 2 (synthesized views lie between capture poses)")
    if len(test) < len(BINS):
        raise ValueError(f"--capture-every {capture_every} leaves {len(test)} test frames of {n}; need >= 3")
    t, r = pose_distance(T_world_cam[test], T_world_cam[cap])
    d = t / TRANS_UNIT_M + r / ROT_UNIT_DEG
    j = np.argmin(d, axis=1)
    rows = np.arange(len(test))
    dist = d[rows, j]
    # Terciles by rank (ties broken by frame order): each bin holds a third of the test frames.
    order = np.argsort(dist, kind="stable")
    bin_of = np.empty(len(test), np.int64)
    for b, chunk in enumerate(np.array_split(order, len(BINS))):
        bin_of[chunk] = b
    edges = (float(dist[bin_of == 0].max()), float(dist[bin_of == 1].max()))
    return CaptureSplit(cap, test, cap[j], t[rows, j], r[rows, j], dist, bin_of, edges)


@dataclass(frozen=True)
class SynthPoseConfig:
    """New camera poses around and between the capture poses (robot-height views)."""

    jitter_m: float = 0.15
    """Horizontal offset (perpendicular to gravity), uniform in [-jitter_m, jitter_m] per axis."""
    height_jitter_m: float = 0.03
    """Vertical offset, uniform in +-height_jitter_m: views stay at the capture's (robot's) height."""
    yaw_jitter_deg: float = 15.0
    """Heading change about the gravity axis, uniform in +-yaw_jitter_deg."""


def synth_poses(capture_poses: np.ndarray, m: int, seed: int, up_world=(0.0, 0.0, 1.0),
                config: SynthPoseConfig = SynthPoseConfig()) -> np.ndarray:
    """``m`` camera poses (m, 4, 4) from the capture poses only (C, 4, 4), seeded.

    Each view: a random consecutive capture pair (i, i+1) and u ~ U(0, 1); centre = lerp, rotation =
    slerp between the pair; then a horizontal offset, a small height change and a heading (yaw about
    ``up_world``) change drawn from :class:`SynthPoseConfig`.
    """
    P = np.asarray(capture_poses, np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) < 2:
        raise ValueError(f"capture_poses must be (C >= 2, 4, 4), got {P.shape}")
    if m < 1:
        raise ValueError(f"--synth must be >= 1, got {m}")
    up = np.asarray(up_world, np.float64)
    up = up / np.linalg.norm(up)
    # Two unit vectors spanning the horizontal plane.
    a = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    rng = np.random.default_rng([seed, 15])
    pair = rng.integers(0, len(P) - 1, m)
    u = rng.uniform(0.0, 1.0, m)
    off = rng.uniform(-1, 1, (m, 2)) * config.jitter_m
    dz = rng.uniform(-1, 1, m) * config.height_jitter_m
    yaw = np.radians(rng.uniform(-1, 1, m) * config.yaw_jitter_deg)
    out = np.tile(np.eye(4), (m, 1, 1))
    for k in range(m):
        i = int(pair[k])
        rots = Rotation.from_matrix(P[[i, i + 1], :3, :3])
        R = Slerp([0.0, 1.0], rots)([u[k]]).as_matrix()[0]
        c = (1 - u[k]) * P[i, :3, 3] + u[k] * P[i + 1, :3, 3]
        R_yaw = Rotation.from_rotvec(up * yaw[k]).as_matrix()
        out[k, :3, :3] = R_yaw @ R
        out[k, :3, 3] = c + off[k, 0] * e1 + off[k, 1] * e2 + dz[k] * up
    return out
