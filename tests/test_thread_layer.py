"""``import torch`` before ``presim.runtime.configure()``: numba must not run on torch's spinning OpenMP
runtime."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import {first}
import presim.runtime, numba, numpy as np
presim.runtime.configure()
from presim.imaging.pool import pool_depth_aware
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


BATCH_SCRIPT = """
import torch
import presim.runtime, numba, numpy as np
presim.runtime.configure()
from presim.geometry import Intrinsics, look_at
from presim.numba_threads import SERIAL_MAX_PIXELS
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S
K = Intrinsics.from_fov(256, 200, 60.0)
small = K.scaled(64, 50)
assert K.width * K.height > SERIAL_MAX_PIXELS >= small.width * small.height
r = Renderer(S.make_scene(S.room_rects(), S.orbit_poses(6), K.scaled(128, 100)), RenderConfig(max_views=6))
poses = np.stack([look_at((x, -1.0, 1.25), (0.2 * x, 0.5, 0.4)) for x in np.linspace(-0.3, 0.3, 4)])
for step in range(3):
    poses[:, 0, 3] += 0.03
    big = r.render_batch(poses, K)  # parallel kernels here
    outs = r.render_batch(poses, small)  # serial twins here, later views warped on the helper thread
ahead = r.executor._ahead
print(numba.threading_layer(), sum(int(o.valid.sum()) > 0 for o in big + outs), 0 if ahead is None else ahead.taken)
"""


def test_frames_and_helper_threads_under_the_work_queue_layer():
    # numba's work queue aborts the process when two threads launch parallel kernels at once: the
    # warp-ahead helper must run only serial kernels while
    # frames run parallel kernels (large) or their serial twins (small).
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    out = subprocess.run([sys.executable, "-c", BATCH_SCRIPT], env=e, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    layer, n_frames, taken = out.stdout.split()
    assert layer == "workqueue" and n_frames == "8" and int(taken) > 0
