"""presim/runtime.py: ``configure()`` applies the process settings (glibc malloc keeps freed memory: no
page faults per frame, unless opted out; OpenMP wait policy); ``import presim`` applies none."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from presim import runtime


class _FakeLibc:
    def __init__(self, ok: int = 1):
        self.calls: list[tuple[int, int]] = []
        self.ok = ok

        def mallopt(param, value):
            self.calls.append((param, value))
            return self.ok

        self.mallopt = mallopt


@pytest.fixture
def fresh(monkeypatch):
    """The module as before its first call, with a fake libc and none of the opt-out variables."""
    monkeypatch.setattr(runtime, "_applied", None)
    monkeypatch.setattr(runtime.sys, "platform", "linux")
    for v in runtime._USER_VARS + ("PRESIM_KEEP_FREED_MEMORY",):
        monkeypatch.delenv(v, raising=False)
    libc = _FakeLibc()
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: libc)
    return libc


def test_sets_both_thresholds_once(fresh):
    assert runtime.keep_freed_memory() is True
    assert fresh.calls == [(-3, 32 << 20), (-1, 256 << 20)]  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    assert runtime.keep_freed_memory() is True
    assert len(fresh.calls) == 2  # idempotent


@pytest.mark.parametrize("var,value", [("PRESIM_KEEP_FREED_MEMORY", "0"), ("MALLOC_TRIM_THRESHOLD_", "1000"),
                                       ("MALLOC_MMAP_THRESHOLD_", "1000"), ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=1")])
def test_user_choices_win(fresh, monkeypatch, var, value):
    monkeypatch.setenv(var, value)
    assert runtime.keep_freed_memory() is False
    assert fresh.calls == []


def test_not_glibc_or_refused(fresh, monkeypatch):
    fresh.ok = 0  # mallopt refused the value
    assert runtime.keep_freed_memory() is False
    monkeypatch.setattr(runtime, "_applied", None)

    def no_libc(name):
        raise OSError("libc.so.6: cannot open shared object file")

    monkeypatch.setattr(runtime.ctypes, "CDLL", no_libc)
    assert runtime.keep_freed_memory() is False
    monkeypatch.setattr(runtime, "_applied", None)
    monkeypatch.setattr(runtime.sys, "platform", "darwin")
    assert runtime.keep_freed_memory() is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc is Linux-only")
def test_configure_applies_it_on_this_machine():
    env = {k: v for k, v in os.environ.items() if k not in runtime._USER_VARS + ("PRESIM_KEEP_FREED_MEMORY",)}
    code = "import presim.runtime as r; r.configure(); r.configure(); print(r._applied)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True"]
    env["PRESIM_KEEP_FREED_MEMORY"] = "0"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["False"]


IMPORT_IS_QUIET = """
import os, sys, warnings
import numpy  # its own import adds warning filters: taken before the snapshot
env0, hooks0, filters0 = dict(os.environ), list(sys.meta_path), list(warnings.filters)
import presim, presim.runtime, presim.capture.scene, presim.geometry
assert dict(os.environ) == env0, sorted(set(os.environ.items()) ^ set(env0.items()))
assert sys.meta_path == hooks0, sys.meta_path
assert warnings.filters == filters0, warnings.filters[:3]
assert presim.runtime._applied is None and "gymnasium" not in sys.modules
presim.runtime.configure()
assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE" and sys.meta_path == hooks0
assert any(f[1] is not None and f[1].pattern.startswith("The TBB") for f in warnings.filters)
print("ok")
"""


def test_import_presim_leaves_the_process_alone():
    """``import presim`` (and leaf modules) changes no environment variable, import hook or warning
    filter and calls no mallopt; ``configure()`` is what applies the settings."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    out = subprocess.run([sys.executable, "-c", IMPORT_IS_QUIET], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok"]


def test_configure_keeps_the_users_wait_policy(monkeypatch):
    monkeypatch.setattr(runtime, "_configured", False)
    monkeypatch.setattr(runtime, "keep_freed_memory", lambda: False)
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    runtime.configure()
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"
