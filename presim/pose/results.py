"""Reader for BOP'19 pose results CSV files.

Format (https://bop.felk.cvut.cz/challenges/bop-challenge-2019/): a header line
``scene_id,im_id,obj_id,score,R,t,time`` then one estimate per line; ``R`` is 9 numbers
(row-major, space-separated), ``t`` 3 numbers in **mm**, ``time`` seconds (-1 if unknown).
Several estimates per (scene, image, object) are allowed; the evaluator keeps the highest scores.

Bad rows are never turned into a silent zero: each one becomes a :class:`Rejection` (line number,
reason, text) that the evaluator counts and reports, or, with ``strict=True``, a ``ValueError``
naming the file and line. A wrong header is always an error.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from presim.datasets.bop_reader import BopDataset, MM_TO_M
from presim.geometry import quat_xyzw_to_R
from presim.io_utils import atomic_write_text

__all__ = ["Estimate", "Rejection", "BopResults", "read_bop_results", "write_bop_results", "estimates_from_gt", "HEADER"]

HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
MAX_ROW_CHARS = 4096
"""Longest accepted row; a valid row is ~150-300 characters (9 + 3 numbers)."""


@dataclass(frozen=True)
class Estimate:
    """One pose estimate of a results file."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    """Confidence; higher is better."""
    R: np.ndarray
    """(3, 3) rotation model -> camera."""
    t_m: np.ndarray
    """(3,) translation model -> camera, metres (converted from the file's mm)."""
    time_s: float
    """Run time reported for the image (-1 = unknown)."""
    line: int
    """1-based line number in the file."""


@dataclass(frozen=True)
class Rejection:
    """A row the reader refused, with why."""

    line: int
    reason: str
    text: str
    obj_id: int | None = None
    """Object id when it could be parsed (for per-object reject counts)."""


@dataclass(frozen=True)
class BopResults:
    """Parsed results file: accepted estimates and rejected rows."""

    path: Path
    estimates: list[Estimate] = field(default_factory=list)
    rejections: list[Rejection] = field(default_factory=list)


def _parse_row(row: list[str], known_obj_ids, rot_tol: float) -> tuple[Estimate | None, str | None, int | None]:
    if len(row) != 7:
        return None, f"expected 7 comma-separated fields, got {len(row)}", None
    try:
        scene_id, im_id, obj_id = int(row[0]), int(row[1]), int(row[2])
    except ValueError:
        return None, "scene_id/im_id/obj_id are not integers", None
    if known_obj_ids is not None and obj_id not in known_obj_ids:
        return None, f"unknown obj_id {obj_id}", obj_id
    try:
        score = float(row[3])
        R = np.array(row[4].split(), dtype=np.float64)
        t = np.array(row[5].split(), dtype=np.float64)
        time_s = float(row[6]) if row[6].strip() else -1.0
    except ValueError:
        return None, "non-numeric score/R/t/time", obj_id
    if R.size != 9:
        return None, f"R has {R.size} numbers, expected 9", obj_id
    if t.size != 3:
        return None, f"t has {t.size} numbers, expected 3", obj_id
    if not (np.isfinite(score) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None, "non-finite score/R/t (NaN or inf)", obj_id
    R = R.reshape(3, 3)
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > rot_tol or det < 0:
        return None, f"R is not a rotation (max |R R^T - I| = {err:.3g}, det = {det:.3g})", obj_id
    return Estimate(scene_id, im_id, obj_id, score, R, t * MM_TO_M, time_s, 0), None, obj_id  # mm -> m


def read_bop_results(path: str | Path, known_obj_ids=None, rot_tol: float = 1e-2,
                     strict: bool = False) -> BopResults:
    """Read a BOP'19 results CSV.

    Args:
        path: the CSV file.
        known_obj_ids: object ids of the dataset; rows with other ids are rejected (None: no check).
        rot_tol: max |R R^T - I| accepted (LM-O's own GT rotations are up to 2e-3 off). Rotations
            are used as given, like bop_toolkit does.
        strict: raise ``ValueError`` on the first bad row instead of collecting rejections.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: results file not found")
    text = path.read_text(encoding="utf-8", errors="replace")
    known = None if known_obj_ids is None else {int(o) for o in known_obj_ids}
    header = None
    estimates: list[Estimate] = []
    rejections: list[Rejection] = []
    # One row per line (BOP rows have no quoted newlines). Oversized lines are rejected before the
    # csv module sees them (its field limit would raise for the whole file).
    for lineno, line in enumerate(text.splitlines(), start=1):
        if len(line) > MAX_ROW_CHARS:
            if header is None:
                raise ValueError(f"{path}: line {lineno}: header line of {len(line)} characters")
            reason = f"row of {len(line)} characters (at most {MAX_ROW_CHARS})"
            if strict:
                raise ValueError(f"{path}: line {lineno}: {reason}")
            rejections.append(Rejection(lineno, reason, line[:200], None))
            continue
        try:
            row = next(csv.reader([line]), [])
        except csv.Error as e:
            row = None
            reason = f"unreadable CSV row ({e})"
        if row is None:
            if header is None or strict:
                raise ValueError(f"{path}: line {lineno}: {reason}")
            rejections.append(Rejection(lineno, reason, line[:200], None))
            continue
        if not row or all(not c.strip() for c in row):
            continue  # blank lines
        if header is None:
            header = [c.strip() for c in row]
            if header != HEADER:
                raise ValueError(f"{path}: line {lineno}: expected header '{','.join(HEADER)}', got '{','.join(row)}'")
            continue
        est, reason, obj_id = _parse_row([c.strip() for c in row], known, rot_tol)
        if est is None:
            if strict:
                raise ValueError(f"{path}: line {lineno}: {reason}")
            rejections.append(Rejection(lineno, reason, ",".join(row)[:200], obj_id))
            continue
        estimates.append(Estimate(est.scene_id, est.im_id, est.obj_id, est.score, est.R, est.t_m, est.time_s, lineno))
    if header is None:
        raise ValueError(f"{path}: empty results file (no header)")
    return BopResults(path=path, estimates=estimates, rejections=rejections)


def write_bop_results(path: str | Path, estimates: list[Estimate]) -> None:
    """Write estimates as a BOP'19 CSV (t converted to mm), atomically."""

    lines = [",".join(HEADER)]
    for e in estimates:
        R = " ".join(f"{v:.9g}" for v in np.asarray(e.R).reshape(-1))
        t = " ".join(f"{v / MM_TO_M:.9g}" for v in np.asarray(e.t_m).reshape(-1))  # m -> mm
        lines.append(f"{e.scene_id},{e.im_id},{e.obj_id},{e.score:.9g},{R},{t},{e.time_s:.6g}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def estimates_from_gt(dataset_dir: str | Path, split: str = "test", noise_t_m: float = 0.0,
                      noise_rot_deg: float = 0.0, seed: int = 0) -> list[Estimate]:
    """Estimates made from a dataset's own ground truth, optionally perturbed (seeded).

    A self-check and a calibrated baseline: with no noise the evaluator must score 100%; with noise
    ``noise_t_m`` (per-axis std of the translation error, metres) and ``noise_rot_deg`` (std of the
    rotation angle about a random axis) the scores fall by amounts that can be checked on paper.
    """
    ds = BopDataset(dataset_dir, split=split)
    rng = np.random.default_rng(seed)
    out: list[Estimate] = []
    for scene_id in ds.scene_ids():
        for im_id, insts in sorted(ds.scene_gt(scene_id).items()):
            for g in insts:
                R, t = np.asarray(g.R_m2c, float), np.asarray(g.t_m2c_m, float)
                if noise_rot_deg > 0:
                    axis = rng.normal(size=3)
                    axis /= np.linalg.norm(axis)
                    ang = np.deg2rad(noise_rot_deg) * rng.normal()
                    q = np.r_[axis * np.sin(ang / 2), np.cos(ang / 2)]
                    R = quat_xyzw_to_R(q) @ R
                if noise_t_m > 0:
                    t = t + rng.normal(scale=noise_t_m, size=3)
                out.append(Estimate(scene_id, im_id, g.obj_id, 1.0, R, t, -1.0, 0))
    return out
