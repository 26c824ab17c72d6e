"""The README's quickstart runs top to bottom (issue 45): every ``presim`` line of its bash block, in
order, in a fresh folder beside ``../shared/data`` (a link), as written; ``presim teleop`` runs until
it prints its URL and is then stopped with Ctrl-C (SIGINT), as a user would. Each command must exit
0 and print the first line of the expected output that the README shows after it (``#>``)."""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def quickstart() -> list[tuple[list[str], str]]:
    """``(argv after 'presim', expected text)`` of each command of the quickstart block."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Quickstart[^\n]*\n.*?```bash\n(.*?)```", text, re.S).group(1)
    cmds: list[tuple[list[str], str]] = []
    for line in block.splitlines():
        if line.startswith("#>") and cmds:
            cmds[-1] = (cmds[-1][0], line[2:].strip())
        elif line.startswith("presim "):
            cmds.append((shlex.split(line, comments=True)[1:], ""))
    return cmds


def test_quickstart_order():
    names = [argv[0] for argv, _ in quickstart()]
    assert names == ["import", "info", "align", "render", "drive", "view", "teleop"]
    assert all(expected for _, expected in quickstart())


def _fragment(expected: str) -> str:
    """The first words the command prints verbatim (up to '...' or a variable number)."""
    return re.split(r" \.\.\.|\d+\.\d+ s|http", expected)[0].split(",")[0].strip()


@pytest.mark.slow
def test_quickstart_runs(tmp_path, shared_data):
    apc = shared_data("apc_cardboard_bin_kinfu50")
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "data").symlink_to(apc.parent, target_is_directory=True)
    work = tmp_path / "work"
    work.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    for argv, expected in quickstart():
        cmd = [sys.executable, "-m", "presim", *argv]
        if argv[0] == "teleop":
            p = subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            t0, out = time.monotonic(), ""
            try:
                while "open http://127.0.0.1:" not in out and time.monotonic() - t0 < 120 and p.poll() is None:
                    out += p.stdout.readline()
            finally:
                p.send_signal(signal.SIGINT)
                out += p.communicate(timeout=60)[0]
            assert "open http://127.0.0.1:" in out, out
        else:
            r = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=600)
            out = r.stdout
            assert r.returncode == 0, f"presim {shlex.join(argv)}:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
        frag = " ".join(_fragment(expected).split())
        assert frag in " ".join(out.split()), f"presim {argv[0]}: expected {frag!r} (spaces aside) in:\n{out}"
    for made in ("out/apc/poses_refined.json", "out/render", "out/drive/recording.mcap", "out/drive.rrd", "out/drive.png"):
        assert (work / made).exists(), made
