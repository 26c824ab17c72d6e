"""``import torch`` before ``import presim``: numba must not run on torch's spinning OpenMP runtime."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import {first}
import presim, numba, numpy as np
from presim.synthesis.lod import pool_depth_aware
pool_depth_aware(np.ones((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8))  # a parallel kernel
print(numba.threading_layer(), __import__("os").environ.get("OMP_WAIT_POLICY"))
"""


def _run(first: str, **env) -> str:
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    e.update(env)
    out = subprocess.run([sys.executable, "-c", SCRIPT.format(first=first)], env=e, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_torch_first_switches_numba_to_its_work_queue():
    assert _run("torch") == ["workqueue", "PASSIVE"]


def test_presim_first_keeps_openmp():
    layer, policy = _run("json")
    assert policy == "PASSIVE" and layer != "workqueue"


@pytest.mark.slow
def test_user_settings_win():
    # The user set the wait policy: presim changes nothing, even after torch.
    assert _run("torch", OMP_WAIT_POLICY="ACTIVE") == ["omp", "ACTIVE"]
    assert _run("torch", NUMBA_THREADING_LAYER="omp")[0] == "omp"
