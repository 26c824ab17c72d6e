"""Child processes that end with the process that started them.

presim starts helper processes: the ROS master and ``/rosout`` (``presim ros``), ``roslaunch``, the
rerun web viewer (``presim view --web``, ``--viewer web``). Each leads its own process group (so a
Ctrl-C in the terminal reaches presim, which stops them in order), which also means nothing stops
them when presim dies without cleaning up (SIGKILL, OOM killer, a crash). :func:`die_with_parent`
closes that gap on Linux: passed as ``preexec_fn``, it asks the kernel (``prctl(PR_SET_PDEATHSIG)``)
to send the child a signal when its parent dies; the flag survives ``exec``.

The kernel sends the signal when the *thread* that forked the child ends, not the process: start
children from a thread that lives as long as they should (the main thread, as every caller here
does). Elsewhere than Linux it is a no-op (``None``).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
from collections.abc import Callable

__all__ = ["die_with_parent", "stop_group"]

_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGKILL) -> Callable[[], None] | None:
    """A ``preexec_fn`` that makes the child receive ``sig`` when this process dies (Linux), or None.

    The libc function is looked up here, in the parent: between fork and exec the child only calls
    it (no import, no allocation). If the parent is already gone by then, the child ends at once."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = (ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong)
    prctl.restype = ctypes.c_int
    parent = os.getpid()
    sig = int(sig)

    def preexec() -> None:
        prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before the flag was set
            os.kill(os.getpid(), sig)

    return preexec


def stop_group(p: subprocess.Popen | None, first: int = signal.SIGTERM, timeout_s: float = 5.0) -> int | None:
    """Stop the process group led by ``p`` (started with ``start_new_session=True``): ``first``, then
    SIGKILL after ``timeout_s``. Returns its exit code (None if it was not started)."""
    if p is None:
        return None
    for sig, wait_s in ((first, timeout_s), (signal.SIGKILL, 5.0)):
        if p.poll() is not None:
            break
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            break
        try:
            p.wait(wait_s)
            break
        except subprocess.TimeoutExpired:
            continue
    return p.wait()
