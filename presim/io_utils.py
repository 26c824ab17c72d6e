"""Atomic output helpers shared by every writer (scenes, renders, recordings, datasets).

Rule: nothing that looks complete is ever half-written. Files are written to a temporary name in the
same folder and renamed into place; folders are built under ``<name>.partial`` and renamed at the end.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "atomic_dir",
           "write_png", "read_image", "progress", "DiskFullError", "open_npy_for_writing", "disk_full_error",
           "free_disk_bytes", "FolderBusyError", "folder_lock", "LOCK_FILE"]


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


# ---- disk space ---------------------------------------------------------------------------------

def format_size(n: float) -> str:
    """``n`` bytes as "1.5 GiB", "300.0 KiB", "12 B"."""
    for unit, div in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(n) >= div:
            return f"{n / div:.1f} {unit}"
    return f"{int(n)} B"


class DiskFullError(OSError):
    """Not enough free space for an output; the message names the path and the bytes needed."""

    def __init__(self, path: str | os.PathLike, needed_bytes: int, free_bytes: int | None = None):
        self.path, self.needed_bytes = Path(path), int(needed_bytes)
        free = "" if free_bytes is None else f", {format_size(free_bytes)} free"
        super().__init__(errno.ENOSPC, f"{path}: no space left on device: needs {self.needed_bytes} bytes "
                                       f"({format_size(self.needed_bytes)}){free}; nothing was kept")

    def __str__(self) -> str:
        return self.strerror


def free_disk_bytes(path: str | os.PathLike) -> int:
    """Bytes an unprivileged writer may still use on the file system of ``path`` (or of its nearest
    existing parent)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    st = os.statvfs(p)
    return st.f_bavail * st.f_frsize


def disk_full_error(e: OSError, path: str | os.PathLike, needed_bytes: int) -> OSError:
    """``e`` as a :class:`DiskFullError` when it is ENOSPC / EDQUOT / EFBIG, else ``e`` itself."""
    if getattr(e, "errno", None) in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        try:
            free = free_disk_bytes(path)
        except OSError:
            free = None
        return DiskFullError(path, needed_bytes, free)
    return e


def open_npy_for_writing(path: str | os.PathLike, dtype, shape: tuple[int, ...]) -> np.memmap:
    """``np.lib.format.open_memmap(path, "w+", ...)`` with every byte of the file reserved first.

    A memory map over a sparse file dies with SIGBUS (no message, exit 135) when the disk fills
    while its pages are written back; ``posix_fallocate`` makes the file system hand out the blocks
    up front, so a full disk is an ordinary :class:`DiskFullError` (path and bytes needed) before
    anything is written, and the half-made file is removed.
    """
    path = Path(path)
    arr = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    size = os.path.getsize(path)
    del arr
    try:
        fd = os.open(path, os.O_RDWR)
        try:
            os.posix_fallocate(fd, 0, size)
        finally:
            os.close(fd)
    except OSError as e:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        raise disk_full_error(e, path, size) from None
    return np.lib.format.open_memmap(path, mode="r+")


def write_npy_atomic(dst: str | os.PathLike, dtype, shape: tuple[int, ...], fill) -> Path:
    """Write ``dst`` (a ``.npy``) through ``dst.partial``: ``fill(array)`` writes into a memory map of
    ``shape`` (:func:`open_npy_for_writing`), which is then renamed into place; on any error the
    partial file is removed, so a ``dst`` that exists is complete. Returns ``dst``."""
    dst = Path(dst)
    partial = dst.with_name(dst.name + ".partial")
    arr = open_npy_for_writing(partial, dtype, shape)
    try:
        fill(arr)
        arr.flush()
    except BaseException:
        del arr
        partial.unlink(missing_ok=True)
        raise
    del arr
    os.replace(partial, dst)
    return dst


# ---- one writer per folder ----------------------------------------------------------------------

LOCK_FILE = ".presim.lock"
"""Advisory lock file a command holds while it writes into a folder (a scene, a BOP scene)."""


class FolderBusyError(OSError):
    """Another command holds the folder's lock (``--no-wait``); the message names the holder."""

    def __init__(self, message: str):
        super().__init__(errno.EBUSY, message)

    def __str__(self) -> str:
        return self.strerror


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
        d = json.loads(text) if text else {}
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(d.get("since", 0))))
        return f"`{d.get('command', 'presim')}` (pid {d.get('pid', '?')}, since {since})"
    except (OSError, ValueError, TypeError):
        return "another presim command"


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, command: str, wait: bool = True,
                log=None) -> Iterator[Path]:
    """Hold the advisory lock (``flock`` on ``FOLDER/.presim.lock``) of a folder that a command writes
    into, so that two commands never write into one scene at once.

    When another process (or another open of the file) holds it: with ``wait`` a one-line message
    naming the holder goes to ``log`` (default: stderr) and the call blocks until it is free;
    without, :class:`FolderBusyError` names the holder. The lock is released when the block ends
    or the process dies (the kernel drops it); the file itself stays (removing it would let a
    waiter lock a file no longer in the folder).
    """
    folder = Path(folder)
    lock_path = folder / LOCK_FILE
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, _FILE_MODE)
    except OSError as e:
        raise OSError(e.errno, f"{folder}: cannot lock the folder for writing ({e.strerror})") from None
    held = False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            if not wait:
                raise FolderBusyError(f"{folder}: busy: {holder} is writing into it; wait for it to finish "
                                      "or run without --no-wait") from None
            msg = f"{folder}: waiting for {holder} to finish writing into it (Ctrl-C to give up)"
            (log or (lambda s: print(s, file=sys.stderr, flush=True)))(msg)
            fcntl.flock(fd, fcntl.LOCK_EX)
        held = True
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps({"command": command, "pid": os.getpid(), "since": time.time()}).encode(), 0)
        yield lock_path
    finally:
        if held:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)  # no stale holder; the empty file is the same after every run
        os.close(fd)  # releases the flock
