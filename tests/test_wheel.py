"""The installable package (issue 45): ``python -m build`` gives a wheel and an sdist with the package
data (launch files, teleop page, robot URDFs); the wheel installed into a fresh venv outside the
checkout runs ``presim demo``.

Offline and fast: ``--no-isolation`` builds with the installed setuptools, and the fresh venv (no
pip, no packages) sees the test interpreter's site-packages through a plain ``.pth`` path line, so
the dependencies need no download; the wheel itself goes in with ``pip install --no-deps --no-index``.
A path added that way is not a site dir, so the checkout's editable install (its own ``.pth`` hook)
stays out: ``presim`` is imported from the venv. About 2 minutes, most of it numba compiling the
kernels of the fresh install.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DATA = ("presim/outputs/launch/presim.launch", "presim/outputs/launch/package.xml",
                "presim/outputs/launch/presim_node", "presim/outputs/teleop/static/index.html",
                "presim/outputs/teleop/static/app.js", "presim/sim/robots/presim_bot.urdf",
                "presim/sim/robots/free_camera.urdf")


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PRESIM_NO_PROGRESS"] = "1"
    return env


@pytest.mark.slow
def test_wheel_installs_and_runs_demo(tmp_path):
    pytest.importorskip("build", reason="`build` is in the [test] extras (scripts/setup.sh installs it)")
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "__pycache__", "out", "build", "dist", "*.egg-info", ".pytest_cache", ".hypothesis",
        "*.rrd", "*.mcap"))
    build_env = dict(os.environ)  # `build` may come from PYTHONPATH here
    subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(tmp_path / "dist"), str(src)],
                   check=True, capture_output=True, env=build_env, cwd=tmp_path, timeout=300)
    wheel = next((tmp_path / "dist").glob("presim-*.whl"))
    sdist = next((tmp_path / "dist").glob("presim-*.tar.gz"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert set(PACKAGE_DATA) <= names
    meta = zipfile.ZipFile(wheel).read(f"{wheel.name.split('-py3')[0]}.dist-info/METADATA").decode()
    assert "Requires-Python: <3.12,>=3.11" in meta and "Provides-Extra: all" in meta
    with tarfile.open(sdist) as t:
        top = t.getnames()[0].split("/")[0]
        assert {f"{top}/{p}" for p in PACKAGE_DATA} <= set(t.getnames())

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    purelib = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True, env=_env()).stdout.strip()
    (Path(purelib) / "_presim_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    subprocess.run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, env=_env(), cwd=tmp_path, timeout=300)
    where = subprocess.run([py, "-c", "import presim; print(presim.__file__)"], check=True, capture_output=True,
                           text=True, env=_env(), cwd=tmp_path).stdout.strip()
    assert Path(where).is_relative_to(venv), where
    r = subprocess.run([venv / "bin" / "presim", "demo", "demo", "--steps", "10", "--bop-frames", "2"],
                       capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "ADD(-S) AUC 1.000" in r.stdout
    assert (tmp_path / "demo" / "drive.rrd").is_file() and (tmp_path / "demo" / "bop").is_dir()
