"""Atomic writers: complete files only, with the permissions a plain open() would give."""

from __future__ import annotations

import os
import stat

import pytest

from presim.io_utils import atomic_dir, atomic_write_bytes


def test_atomic_write_gives_umask_permissions_and_no_temp_left(tmp_path):
    mask = os.umask(0o022)
    try:
        p = tmp_path / "a" / "x.bin"
        atomic_write_bytes(p, b"abc")
    finally:
        os.umask(mask)
    assert p.read_bytes() == b"abc"
    from presim.io_utils import _FILE_MODE

    assert stat.S_IMODE(p.stat().st_mode) == _FILE_MODE
    assert _FILE_MODE & 0o044  # readable by others under the usual umask (not mkstemp's 0600)
    assert [q.name for q in p.parent.iterdir()] == ["x.bin"]


def test_atomic_dir_removes_partial_on_error_and_refuses_existing(tmp_path):
    dst = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with atomic_dir(dst) as tmp:
            (tmp / "f").write_text("half")
            raise RuntimeError("interrupted")
    assert not dst.exists() and not (tmp_path / "out.partial").exists()
    with atomic_dir(dst) as tmp:
        (tmp / "f").write_text("done")
    with pytest.raises(FileExistsError, match="--overwrite"):
        with atomic_dir(dst):
            pass
    assert (dst / "f").read_text() == "done"
