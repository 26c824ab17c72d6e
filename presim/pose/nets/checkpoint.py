"""Run folders of ``presim pose-train``: the checkpoint file (written atomically, read with
``weights_only=True``) and :func:`load_run`, what training, prediction and segmentation read back.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import torch

__all__ = ["CHECKPOINT", "save_checkpoint", "load_checkpoint", "load_run"]

CHECKPOINT = "checkpoint_last.pt"


def save_checkpoint(path: Path, state: dict) -> None:
    """``torch.save`` to a temporary file in the same folder, then an atomic rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_checkpoint(path: Path, device: str = "cpu") -> dict:
    """A checkpoint of :func:`save_checkpoint` (tensors, numbers, strings only: ``weights_only=True``)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # a truncated or foreign file: one line naming it
        raise ValueError(f"{path}: unreadable checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:200]})") from None


def load_run(run_dir: str | Path) -> tuple[dict, dict]:
    """``(config.json, checkpoint)`` of a run folder, with one-line errors."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"{run_dir / 'config.json'}: not a pose-train run folder")
    with open(run_dir / "config.json", encoding="utf-8") as f:
        cfg = json.load(f)
    return cfg, load_checkpoint(run_dir / CHECKPOINT)
