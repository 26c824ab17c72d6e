"""TUM trajectories: ``stamp x y z qx qy qz qw`` per line, a pose ``T_world_cam`` (or any ``T_a_b``)
in metres with a unit quaternion, scalar last, stamps in seconds.

One strict reader (:func:`read_tum`) and one writer (:func:`write_tum`, :func:`tum_line`). The TUM
RGB-D importer's ``groundtruth.txt`` reading (``presim.capture.importers.tum``) is a different
concept: mocap samples, sorted and interpolated at image stamps, so it keeps its own reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from presim.geometry import pose_from_tum, pose_to_tum
from presim.io_utils import atomic_write_text

__all__ = ["TUM_HEADER", "read_tum", "tum_line", "write_tum"]

TUM_HEADER = "# stamp_s x y z qx qy qz qw (T_world_cam, camera optical frame)"
"""First line :func:`write_tum` writes (readers skip ``#`` lines)."""

_QUAT_NORM_TOL = 0.01


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory strictly: returns ``(stamps_s (N,), poses (N, 4, 4))``.

    ``#`` starts a comment (whole line or the rest of one); commas count as spaces. Every other
    line holds 8 finite numbers with a unit quaternion (norm within 1 %), stamps strictly increase
    and there is at least one pose. Errors are ``ValueError`` naming ``file:line`` (a missing file
    is ``FileNotFoundError``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    stamps, poses = [], []
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
        poses.append(pose_from_tum(vals[1:]))
    if not stamps:
        raise ValueError(f"{path}: empty trajectory")
    return np.array(stamps), np.stack(poses)


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
