"""Atomic output helpers shared by every writer (scenes, renders, recordings, datasets).

Rule: nothing that looks complete is ever half-written. Files are written to a temporary name in the
same folder and renamed into place; folders are built under ``<name>.partial`` and renamed at the end.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "atomic_dir",
           "write_png", "read_image", "progress"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()
"""Mode of written files: what ``open()`` would give (mkstemp's 0600 would hide them from others)."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, _FILE_MODE)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj, indent: int | None = 2) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent) + "\n")


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB uint8 (H,W,3), gray uint8 (H,W) or uint16 (H,W) image as PNG, atomically."""
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"{path}: color PNGs must be uint8 HxWx3, got {img.dtype} {img.shape}")
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.dtype not in (np.uint8, np.uint16, np.bool_):
        raise ValueError(f"{path}: single-channel PNGs must be uint8/uint16, got {img.dtype}")
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def read_image(path: str | os.PathLike, *, kind: str) -> np.ndarray:
    """Read an image with a clear error. ``kind``: ``'color'`` -> uint8 RGB (H,W,3);
    ``'depth'`` / ``'mask'`` -> the file's single channel unchanged (uint16/uint8)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    flags = cv2.IMREAD_COLOR if kind == "color" else cv2.IMREAD_UNCHANGED
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ValueError(f"{path}: unreadable or corrupt image")
    if kind == "color":
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.ndim != 2:
        raise ValueError(f"{path}: expected a single-channel {kind} image, got shape {img.shape}")
    return img


@contextlib.contextmanager
def atomic_dir(dst: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder under ``<dst>.partial`` and rename it to ``dst`` only when the block succeeds.

    An existing ``dst`` is an error unless ``overwrite``; then it is replaced only after the new
    folder is complete. On failure the partial folder is removed.
    """
    dst = Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: already exists (use --overwrite / overwrite=True to replace it)")
    tmp = dst.with_name(dst.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if dst.exists():
        old = dst.with_name(dst.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(dst, old)
        os.replace(tmp, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, dst)


_progress_enabled = True


def set_progress(enabled: bool) -> None:
    """Turn every :func:`progress` bar of this process on or off (``presim ... --quiet``: off)."""
    global _progress_enabled
    _progress_enabled = bool(enabled)


def progress_on() -> bool:
    """Whether :func:`progress` shows bars: stderr is a terminal, no ``--quiet``, no PRESIM_NO_PROGRESS=1."""
    try:
        tty = sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stderr
        tty = False
    return _progress_enabled and tty and os.environ.get("PRESIM_NO_PROGRESS") != "1"


def progress(iterable=None, *, total: int | None = None, desc: str = "", unit: str = "it", disable: bool | None = None):
    """tqdm progress bar on stderr; off (:func:`progress_on`) when stderr is not a terminal, after
    ``--quiet`` or with PRESIM_NO_PROGRESS=1. ``disable``: True/False overrides that."""
    from tqdm.auto import tqdm

    if disable is None:
        disable = not progress_on()
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, dynamic_ncols=True)
