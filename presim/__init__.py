"""PreSim: a photo-realistic RGB-D simulator for robots, built from captured RGB-D images.

Data flow (one sub-package per stage)::

    capture -> depth -> synthesis -> sensors -> sim -> outputs -> datasets -> pose
"""

__version__ = "0.1.0"

import os as _os

# The numba kernels run on OpenMP threads. GNU OpenMP's default lets idle threads spin for a while
# after each parallel region; the renderer launches many short regions between OpenCV/numpy calls,
# so spinning threads stole the cores from them: 2 threads were no faster than 1 on an idle 2-core
# machine and 2.6x slower with one other busy process (benchmarks/bench_render.py, docs/synthesis.md).
# Sleeping idle threads fix both. Read once when libgomp loads, so it is set before any import that
# could load it; a value the user set wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import warnings as _warnings

# numba probes TBB first and warns when the system's TBB is too old, then uses OpenMP: not our
# user's problem, so keep it off their screen.
_warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB version")
