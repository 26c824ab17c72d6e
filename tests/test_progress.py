"""Progress bars (issue 45): on a terminal, off when stderr is not one, after ``--quiet`` or with
PRESIM_NO_PROGRESS=1; ``presim drive`` shows one per step and prints every path it wrote."""

from __future__ import annotations

import io
import sys

import pytest

from presim import io_utils
from presim.capture.store import save_scene
from presim.cli import main
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture()
def tty_stderr(monkeypatch):
    """Call it in the test body to make stderr a terminal (pytest's capture resets sys.stderr after setup)."""
    monkeypatch.delenv("PRESIM_NO_PROGRESS", raising=False)

    def install() -> _Tty:
        err = _Tty()
        monkeypatch.setattr(sys, "stderr", err)
        return err

    yield install
    io_utils.set_progress(True)


def test_progress_on_only_on_a_terminal(tty_stderr, monkeypatch):
    tty_stderr()
    assert io_utils.progress_on()
    io_utils.set_progress(False)
    assert not io_utils.progress_on()
    io_utils.set_progress(True)
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    assert not io_utils.progress_on()
    monkeypatch.delenv("PRESIM_NO_PROGRESS")
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # a pipe or a file
    assert not io_utils.progress_on()


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return save_scene(build_toy_room(ToyRoomConfig(width=64, height=48)), tmp_path_factory.mktemp("toy") / "toy")


def test_drive_shows_progress_and_prints_paths(toy, tmp_path, tty_stderr, capsys):
    err = tty_stderr()
    rec, rrd = tmp_path / "rec", tmp_path / "drive.rrd"
    argv = ["drive", str(toy), "--steps", "4", "--width", "32", "--height", "24", "--record", str(rec), "--rrd", str(rrd)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "drive: 100%" in err.getvalue() and "4/4" in err.getvalue()
    for p in (rec / "recording.mcap", rec / "capture", rrd):
        assert p.exists() and f"wrote {p}\n" in out
    err.seek(0)
    err.truncate()
    assert main(argv[:-4] + ["--quiet"]) == 0
    assert "drive:" not in err.getvalue()
