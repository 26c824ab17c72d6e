"""Every ```python block of README.md and docs/*.md runs (issue 45).

The blocks of one file run in order in one namespace, as a reader would paste them, in a folder laid
out like the README quickstart's: ``out/apc`` (the APC capture imported), ``out/sample`` (a small
sample scene with a floor) and ``../shared/data`` (the real captures). A block that cannot run
standalone is preceded by the line ``<!-- doc-test: skip: REASON -->``; the reason is required.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = re.compile(r"<!--\s*doc-test:\s*skip:\s*(.+?)\s*-->")
FENCE = re.compile(r"^```python[^\n]*\n(.*?)^```", re.S | re.M)


def python_blocks(text: str) -> list[tuple[int, str, str | None]]:
    """``(line, code, skip reason or None)`` of every fenced python block of ``text``."""
    out = []
    for m in FENCE.finditer(text):
        before = text[: m.start()].rstrip().rsplit("\n", 1)[-1]
        skip = SKIP.search(before)
        out.append((text.count("\n", 0, m.start()) + 1, m.group(1), skip.group(1) if skip else None))
    return out


def test_block_extraction():
    text = "a\n```python\nx = 1\n```\n<!-- doc-test: skip: needs ROS -->\n```python\ny\n```\n```bash\nz\n```\n"
    assert python_blocks(text) == [(2, "x = 1\n", None), (6, "y\n", "needs ROS")]


DOCS_WITH_CODE = [p for p in DOC_FILES if python_blocks(p.read_text())]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, shared_data):
    """``work/`` with out/apc and out/sample, and ``../shared/data`` beside it (a link)."""
    from presim.cli import main

    apc = shared_data("apc_cardboard_bin_kinfu50")
    base = tmp_path_factory.mktemp("docs")
    (base / "shared").mkdir()
    (base / "shared" / "data").symlink_to(apc.parent, target_is_directory=True)
    work = base / "work"
    work.mkdir()
    old = Path.cwd()
    os.chdir(work)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["import", "../shared/data/apc_cardboard_bin_kinfu50", "out/apc"]) == 0
            assert main(["sample-scene", "out/sample", "--frames", "8", "--width", "160", "--height", "120"]) == 0
    finally:
        os.chdir(old)
    return work


@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCS_WITH_CODE, ids=[p.name for p in DOCS_WITH_CODE])
def test_python_blocks_run(doc, workdir, monkeypatch):
    monkeypatch.chdir(workdir)
    namespace: dict = {"__name__": f"doc:{doc.name}"}
    for line, code, skip in python_blocks(doc.read_text()):
        if skip is not None:
            assert len(skip) >= 10, f"{doc.name}:{line}: a skip marker needs its reason"
            continue
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                exec(compile(code, f"{doc.name}:{line}", "exec"), namespace)
        except Exception as e:
            raise AssertionError(f"{doc.relative_to(ROOT)} line {line}: the python block failed: {e!r}") from e
