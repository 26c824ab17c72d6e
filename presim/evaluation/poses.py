"""Trajectory metrics (TUM RGB-D benchmark definitions): ATE RMSE and RPE.

- **ATE** (absolute trajectory error): the estimated camera centres are aligned to the reference ones
  by the least-squares rigid transform (Horn / Umeyama, no scale; ``similarity=True`` also fits a
  scale), then the RMSE of the centre differences.
- **RPE** (relative pose error) over ``delta`` frames: ``E_i = (Q_i^-1 Q_{i+d})^-1 (P_i^-1 P_{i+d})``
  (Q reference, P estimate), RMSE of the translation parts and of the rotation angles (degrees).
  No alignment is needed (relative motions).
Frames are matched by timestamp (nearest reference stamp within ``max_dt_s``, reference poses
interpolated between bracketing samples) or by frame id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.formats.tum import interpolate_pose
from presim.geometry import invert

__all__ = ["TrajectoryErrors", "umeyama", "ate_rpe", "match_by_stamp"]


@dataclass(frozen=True)
class TrajectoryErrors:
    ate_rmse_m: float
    rpe_trans_m: float
    rpe_rot_deg: float
    frames_matched: int
    alignment: str
    """"rigid" or "similarity (scale s)"."""
    T_ref_est: np.ndarray
    """The 4x4 alignment applied to the estimate (scale in the rotation block when similarity)."""

    def to_json(self) -> dict:
        return {"ate_rmse_m": self.ate_rmse_m, "rpe_trans_m": self.rpe_trans_m, "rpe_rot_deg": self.rpe_rot_deg,
                "frames_matched": self.frames_matched, "alignment": self.alignment}


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimising sum ||dst_i - (s R src_i + t)||^2 for (N, 3) point sets (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean()) if with_scale else 1.0
    return R, mu_d - s * R @ mu_s, s


def _angle_deg(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(c))


def ate_rpe(T_ref: np.ndarray, T_est: np.ndarray, similarity: bool = False, delta: int = 1) -> TrajectoryErrors:
    """ATE / RPE of matched pose pairs ``(N, 4, 4)`` camera-to-world (see module doc)."""
    T_ref, T_est = np.asarray(T_ref, np.float64), np.asarray(T_est, np.float64)
    if T_ref.shape != T_est.shape or T_ref.ndim != 3 or T_ref.shape[1:] != (4, 4):
        raise ValueError(f"trajectories must both be (N, 4, 4), got {T_ref.shape} and {T_est.shape}")
    n = len(T_ref)
    if n < 3:
        raise ValueError(f"need at least 3 matched poses, got {n}")
    if not (np.all(np.isfinite(T_ref)) and np.all(np.isfinite(T_est))):
        raise ValueError("trajectories contain non-finite poses")
    R, t, s = umeyama(T_est[:, :3, 3], T_ref[:, :3, 3], with_scale=similarity)
    c_al = s * T_est[:, :3, 3] @ R.T + t
    ate = float(np.sqrt(np.mean(np.sum((c_al - T_ref[:, :3, 3]) ** 2, axis=1))))
    d = max(1, int(delta))
    if n <= d:
        raise ValueError(f"RPE delta {d} needs more than {d} poses, got {n}")
    est = T_est.copy()
    est[:, :3, 3] *= s  # a similarity alignment's scale applies to relative translations too
    Q = invert(T_ref[:-d]) @ T_ref[d:]
    P = invert(est[:-d]) @ est[d:]
    E = invert(Q) @ P
    rpe_t = float(np.sqrt(np.mean(np.sum(E[:, :3, 3] ** 2, axis=1))))
    rpe_r = float(np.sqrt(np.mean(_angle_deg(E[:, :3, :3]) ** 2)))
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = s * R, t
    return TrajectoryErrors(ate, rpe_t, rpe_r, n, "rigid" if not similarity else f"similarity (scale {s:.6f})", A)


def match_by_stamp(stamps_est: np.ndarray, ref_stamps: np.ndarray, ref_rows: np.ndarray,
                   max_gap_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(indices of estimated frames matched, reference poses (M, 4, 4) interpolated at their stamps);
    ``ref_stamps``, ``ref_rows``: :func:`presim.formats.tum.read_tum_rows` of the reference."""
    idx, poses = [], []
    for i, t in enumerate(np.asarray(stamps_est, float)):
        T = interpolate_pose(ref_stamps, ref_rows, float(t), max_gap_s)
        if T is not None:
            idx.append(i)
            poses.append(T)
    return np.array(idx, dtype=int), (np.stack(poses) if poses else np.zeros((0, 4, 4)))
