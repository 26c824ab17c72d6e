"""Shared test set-up.

In CI (``CI=true``) a skipped test is a failure: every test must run there (real data from
``../shared/data``, ROS 1 and chromium are installed by ``scripts/setup.sh --test-system``).
Locally, tests whose data or system packages are missing skip with a reason (shown by ``-ra``).
Tests that read a real capture take the :func:`shared_data` fixture: ``shared_data("lmo_scene000002")``
is the folder's path, and a missing folder fails in CI and skips locally.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

import presim.runtime

# The suite runs with the process settings the CLI applies (sleeping OpenMP threads, kept freed
# memory; presim/runtime.py): `import presim` alone applies none.
presim.runtime.configure()

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
"""Real captures (``../shared/data`` relative to the repository root); read only, never copied."""

# A shell that starts the suite as a background job without job control (`make test &`, nohup ... &)
# sets SIGINT to "ignore", and every child inherits it: the Ctrl-C tests' subprocesses (drive,
# recorder, ROS bridge) would then never see their SIGINT. A handler, unlike "ignore", is reset to
# the default in a child at exec, so the children start with Python's usual KeyboardInterrupt.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if IN_CI and rep.skipped and not hasattr(rep, "wasxfail"):
        reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
        rep.outcome = "failed"
        rep.longrepr = f"skipped in CI (CI=true forbids skips): {reason}"


def pytest_sessionstart(session):
    os.environ.setdefault("PRESIM_NO_PROGRESS", "1")


@pytest.fixture(scope="session")
def shared_data() -> Callable[[str], Path]:
    """``shared_data(name)`` -> Path of ``../shared/data/<name>``.

    A missing folder fails the test in CI (``CI`` = 1/true/yes) and skips it with a reason elsewhere.
    Session-scoped so that module-scoped fixtures can use it too.
    """

    def get(name: str) -> Path:
        path = SHARED_DATA / name
        if not path.is_dir():
            if IN_CI:
                pytest.fail(f"real data {path} missing (required in CI)")
            pytest.skip(f"real data {path} not available")
        return path

    return get
