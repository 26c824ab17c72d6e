"""TUM trajectories: ``stamp x y z qx qy qz qw`` per line, a pose ``T_world_cam`` (or any ``T_a_b``)
in metres with a unit quaternion, scalar last, stamps in seconds.

One strict reader, :func:`read_tum_rows` (stamps and ``x y z qx qy qz qw`` rows), which every TUM
trajectory in PreSim goes through: :func:`read_tum` (the same as 4x4 poses: ``presim render --poses``,
trajectory replay), the TUM RGB-D importer's ``groundtruth.txt`` and ``presim eval-poses``
references (rows interpolated at other stamps by :func:`interpolate_pose`). One writer
(:func:`write_tum`, :func:`tum_line`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from presim.geometry import make_pose, pose_from_tum, pose_to_tum, quat_xyzw_to_R
from presim.io_utils import atomic_write_text

__all__ = ["TUM_HEADER", "interpolate_pose", "read_tum", "read_tum_rows", "tum_line", "write_tum"]

TUM_HEADER = "# stamp_s x y z qx qy qz qw (T_world_cam, camera optical frame)"
"""First line :func:`write_tum` writes (readers skip ``#`` lines)."""

_QUAT_NORM_TOL = 0.01


def read_tum_rows(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory strictly: returns ``(stamps_s (N,), rows (N, 7))``, each row
    ``x y z qx qy qz qw`` as in the file (the quaternion not renormalised).

    ``#`` starts a comment (whole line or the rest of one); commas count as spaces. Every other
    line holds 8 finite numbers with a unit quaternion (norm within 1 %), stamps strictly increase
    and there is at least one pose. Errors are ``ValueError`` naming ``file:line`` (a missing file
    is ``FileNotFoundError``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    stamps, rows = [], []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            vals = np.array([float(v) for v in line.replace(",", " ").split()])
        except ValueError:
            raise ValueError(f"{path}:{n}: not a TUM line 'stamp x y z qx qy qz qw': '{line}'") from None
        if len(vals) != 8:
            raise ValueError(f"{path}:{n}: a TUM line has 8 numbers (stamp x y z qx qy qz qw), got {len(vals)}")
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"{path}:{n}: non-finite value in '{line}'")
        qn = np.linalg.norm(vals[4:])
        if qn < 1e-6:
            raise ValueError(f"{path}:{n}: zero quaternion")
        if abs(qn - 1.0) > _QUAT_NORM_TOL:
            raise ValueError(f"{path}:{n}: quaternion norm {qn:.4g} is not 1 (corrupt line?)")
        if stamps and vals[0] <= stamps[-1]:
            raise ValueError(f"{path}:{n}: timestamps must strictly increase ({vals[0]:.9g} after {stamps[-1]:.9g})")
        stamps.append(vals[0])
        rows.append(vals[1:])
    if not stamps:
        raise ValueError(f"{path}: empty trajectory")
    return np.array(stamps), np.stack(rows)


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_tum_rows` as ``(stamps_s (N,), poses (N, 4, 4))``."""
    stamps, rows = read_tum_rows(path)
    return stamps, np.stack([pose_from_tum(r) for r in rows])


def _slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    d = float(q0 @ q1)
    if d < 0:  # shortest arc
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + w * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - w) * th) * q0 + np.sin(w * th) * q1) / np.sin(th)


def interpolate_pose(stamps_s: np.ndarray, rows: np.ndarray, t: float, max_gap_s: float) -> np.ndarray | None:
    """Pose (4, 4) at stamp ``t`` from :func:`read_tum_rows` output: linear in position, slerp in
    rotation between the two samples around ``t``; None outside the range or across a gap longer
    than ``max_gap_s`` (mocap dropouts)."""
    k = int(np.searchsorted(stamps_s, t))
    if k < len(stamps_s) and abs(stamps_s[k] - t) < 1e-9:
        v = rows[k]
        return make_pose(quat_xyzw_to_R(v[3:]), v[:3])
    if k == 0 or k == len(stamps_s):
        return None
    t0, t1 = stamps_s[k - 1], stamps_s[k]
    if t1 - t0 > max_gap_s:
        return None
    w = (t - t0) / (t1 - t0)
    p = (1 - w) * rows[k - 1, :3] + w * rows[k, :3]
    q = _slerp(rows[k - 1, 3:], rows[k, 3:], w)
    return make_pose(quat_xyzw_to_R(q), p)


def tum_line(stamp_s: float, T: np.ndarray) -> str:
    """One TUM line (no newline): stamp and pose with 9 decimals (nanoseconds, nanometres)."""
    return f"{stamp_s:.9f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(T))


def write_tum(path: str | Path, stamps_s: np.ndarray, poses: np.ndarray, header: str = TUM_HEADER) -> None:
    """Write ``(N,)`` stamps and ``(N, 4, 4)`` poses as a TUM file (atomically), ``header`` first."""
    poses = np.asarray(poses, dtype=np.float64)
    if len(stamps_s) == 0 and poses.size == 0:
        poses = poses.reshape(0, 4, 4)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(stamps_s):
        raise ValueError(f"{path}: need (N,) stamps and (N, 4, 4) poses, got {len(stamps_s)} and {poses.shape}")
    lines = [header] if header else []
    lines += [tum_line(float(s), T) for s, T in zip(stamps_s, poses)]
    atomic_write_text(path, "".join(s + "\n" for s in lines))
