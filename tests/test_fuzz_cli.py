"""Issue 16 fuzz suite (bounded, in-process, `pytest -m fuzz`): property tests over the arguments of
render / drive / gen-bop (never a traceback, never past the memory budget) and random byte
corruption of every capture format's files (a named one-line error and nothing written, or a
complete import when the bytes hit pixel data)."""

from __future__ import annotations

import random
import resource
import shutil
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import (  # noqa: E402
    synth_frames, write_bop, write_colmap, write_kinfu, write_nerfstudio, write_tum,
)

from presim.cli import main  # noqa: E402

pytestmark = pytest.mark.fuzz
BUDGET = "256M"
SETTINGS = settings(max_examples=12, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    from presim.capture.store import save_scene
    from presim.testing.toy_scene import build_toy_room

    dst = tmp_path_factory.mktemp("fuzz") / "toyroom"
    save_scene(build_toy_room(), dst)
    return dst


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    monkeypatch.delenv("DISPLAY", raising=False)


# A size: mostly tiny valid ones (cheap renders), plus the adversarial values.
size = st.one_of(st.integers(1, 24), st.sampled_from(["0", "-5", "100000", "nan", "1e9", "x", "3.5", ""]))
real = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32),
                 st.sampled_from(["0", "-1", "nan", "inf", "abc"]))


def _call(capsys, argv: list[str]) -> tuple[int, str]:
    """Run one command in-process: it must return (argparse errors raise SystemExit 2), print at
    most one error line and never a traceback."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse: usage + one error line
        rc = e.code
    _, err = capsys.readouterr()
    assert "Traceback" not in err, err
    errors = [ln for ln in err.splitlines() if "error:" in ln]
    assert rc in (0, 1, 2), (rc, err)
    if rc != 0:
        assert len(errors) == 1, err
    return rc, err


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@given(w=size, h=size, layers=st.one_of(st.integers(-2, 6), st.sampled_from([100000, 10**9])), fx=real)
@SETTINGS
def test_render_args_property(capsys, tmp_path_factory, toy, w, h, layers, fx):
    out = tmp_path_factory.mktemp("r")
    rss0 = _rss_mb()
    rc, err = _call(capsys, ["render", toy, "--frame", "0", "--out", out / "o", "--width", w, "--height", h,
                             "--layers", layers, "--fx", fx, "--max-memory", BUDGET])
    assert _rss_mb() - rss0 < 256, "past the memory budget"
    if rc != 0:
        assert not (out / "o").exists(), "a refused render wrote files"


@given(w=size, h=size, dt=real, steps=st.one_of(st.integers(-1, 3), st.just(10**9)))
@SETTINGS
def test_drive_args_property(capsys, toy, w, h, dt, steps):
    steps = min(int(steps), 3) if isinstance(steps, int) and steps > 3 else steps  # keep runs short
    rss0 = _rss_mb()
    _call(capsys, ["drive", toy, "--steps", steps, "--width", w, "--height", h, "--dt", dt,
                   "--max-memory", BUDGET])
    assert _rss_mb() - rss0 < 256, "past the memory budget"


@given(w=st.sampled_from(["0", "-1", "100000", "nan", "1280"]), h=st.sampled_from(["0", "100000", "720", "x"]),
       workers=st.sampled_from(["0", "1", "64", "-3"]), frames=st.sampled_from(["0", "-1", "1"]))
@SETTINGS
def test_gen_bop_args_property(capsys, tmp_path_factory, toy, w, h, workers, frames):
    out = tmp_path_factory.mktemp("b") / "bop"
    rc, err = _call(capsys, ["gen-bop", toy, "--out", out, "--width", w, "--height", h, "--workers", workers,
                             "--frames", frames, "--max-memory", BUDGET, "--max-new-frames", "0"])
    if rc != 0:
        assert not out.exists(), "a refused gen-bop left a job folder"


# ---- capture files ------------------------------------------------------------------------------
WRITERS = {
    "tum": lambda d, f: write_tum(d, f),
    "kinfu": lambda d, f: write_kinfu(d, f),
    "nerfstudio": lambda d, f: write_nerfstudio(d, f),
    "colmap-text": lambda d, f: write_colmap(d, f, binary=False),
    "colmap-binary": lambda d, f: write_colmap(d, f, binary=True),
    "bop": lambda d, f: write_bop(d / "test" / "000001", f, objects=False),
}


def _corrupt(path: Path, rng: random.Random) -> str:
    data = bytearray(path.read_bytes())
    how = rng.choice(["flip", "truncate", "garbage", "empty"])
    if how == "flip" and data:
        for _ in range(rng.randint(1, 16)):
            data[rng.randrange(len(data))] = rng.randrange(256)
    elif how == "truncate":
        data = data[:rng.randrange(len(data) + 1)]
    elif how == "garbage":
        data = bytearray(rng.randbytes(rng.randint(1, 200)))
    else:
        data = bytearray()
    path.write_bytes(bytes(data))
    return how


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_corrupted_capture_files_give_a_named_error_and_write_nothing(capsys, tmp_path, fmt):
    rng = random.Random(16)
    frames = synth_frames(n=3, w=24, h=18, seed=1)
    clean = tmp_path / "clean"
    WRITERS[fmt](clean, frames)
    files = sorted(p for p in clean.rglob("*") if p.is_file())
    refused = 0
    for trial in range(8):
        src = tmp_path / f"src{trial}"
        shutil.copytree(clean, src)
        victim = src / rng.choice(files).relative_to(clean)
        how = _corrupt(victim, rng)
        dst = tmp_path / f"dst{trial}"
        rc, err = _call(capsys, ["import", src, dst, "--no-floor"])
        if rc != 0:
            refused += 1
            assert not dst.exists() and not any(tmp_path.glob(f"dst{trial}*")), "a refused import wrote files"
            # names the file (or its folder) it could not use
            assert str(src) in err or victim.name in err, (how, victim, err)
        else:
            assert (dst / "scene.json").is_file()  # accepted: a complete scene (e.g. flipped pixel bytes)
    assert refused >= 1, "no corruption was detected at all"
