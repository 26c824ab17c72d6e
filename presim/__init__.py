"""PreSim: a photo-realistic RGB-D simulator for robots, built from captured RGB-D images.

Data flow (one sub-package per stage)::

    capture -> depth -> synthesis -> sensors -> sim -> outputs -> datasets -> pose
"""

__version__ = "0.1.0"

import warnings as _warnings

# numba probes TBB first and warns when the system's TBB is too old, then uses OpenMP: not our
# user's problem, so keep it off their screen.
_warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB version")
