"""PreSim: a photo-realistic RGB-D simulator for robots, built from captured RGB-D images.

Data flow (one sub-package per stage)::

    capture -> depth -> synthesis -> sensors -> sim -> outputs -> datasets -> pose
"""

__version__ = "0.1.0"

# ---- Public API (lazy) -----------------------------------------------------------------------
# `presim.open_scene`, `presim.Scene`, `presim.Simulator` live in presim/api/ (docs/api.md); they
# are imported on first use so that `import presim` does not load numba, OpenCV or the renderer.
_API_NAMES = ("open_scene", "Scene", "Simulator", "RenderConfig")


def __getattr__(name: str):
    if name in _API_NAMES:
        import presim.api

        return getattr(presim.api, name)
    raise AttributeError(f"module 'presim' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API_NAMES))
# ---- end of the public API --------------------------------------------------------------------

import os as _os

# The numba kernels run on OpenMP threads. GNU OpenMP's default lets idle threads spin for a while
# after each parallel region; the renderer launches many short regions between OpenCV/numpy calls,
# so spinning threads stole the cores from them: 2 threads were no faster than 1 on an idle 2-core
# machine and 2.6x slower with one other busy process (benchmarks/bench_render.py, docs/synthesis.md).
# Sleeping idle threads fix both. Read once when libgomp loads, so it is set before any import that
# could load it; a value the user set wins.
import sys as _sys


def _gomp_loaded() -> bool:
    """True when a GNU OpenMP runtime is already loaded in this process (e.g. by ``import torch``)."""
    try:
        with open("/proc/self/maps") as f:
            return "libgomp" in f.read()
    except OSError:  # not Linux: look for the usual importer
        return "torch" in _sys.modules


if "OMP_WAIT_POLICY" not in _os.environ:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    # Too late when libgomp is already loaded (``import torch`` before ``import presim``): it read
    # the policy at load time and spins, and numba's OpenMP layer binds to that runtime (measured:
    # 1.7x the CPU per 640x480 frame, docs/synthesis.md "Threads"). numba's own work queue sleeps
    # like PASSIVE OpenMP (same CPU per frame measured), so use it then, unless the user chose a
    # layer. It is safe here: the simulator renders from one thread at a time.
    if "NUMBA_THREADING_LAYER" not in _os.environ and _gomp_loaded():
        _os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
        if "numba" in _sys.modules:  # read at numba's import; takes effect before its first parallel launch
            _sys.modules["numba"].config.THREADING_LAYER = "workqueue"

# Keep freed heap memory for reuse instead of handing it back to the kernel after every frame
# (presim/runtime.py: 0 instead of ~2 000-4 700 page faults per 640x480 frame).
from presim.runtime import keep_freed_memory as _keep_freed_memory

_keep_freed_memory()

import warnings as _warnings

# numba probes TBB first and warns when the system's TBB is too old, then uses OpenMP: not our
# user's problem, so keep it off their screen.
_warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB version")

# ---- Gymnasium environments -----------------------------------------------------------------
# `import presim` makes `gym.make("PreSim-PointNav-v0", scene=...)` work without importing
# gymnasium itself (1.2 s cold on this machine): when gymnasium is already imported the ids are
# registered now, otherwise right after gymnasium's own import finishes (an import hook). The
# registration only names the entry point; presim.sim.envs loads on gym.make.
GYM_ENV_IDS = (("PreSim-PointNav-v0", False), ("PreSim-PointNavDiscrete-v0", True))


def register_gym_envs() -> None:
    """Register the PreSim environments with gymnasium (idempotent)."""
    import gymnasium as gym

    for env_id, discrete in GYM_ENV_IDS:
        if env_id not in gym.registry:
            # gym.make_vec(id, num_envs=N, scene=..., [workers=W]) makes the batched PointNavVectorEnv
            # (vectorization_mode="sync" / "async": gymnasium's wrappers of N single envs)
            gym.register(id=env_id, entry_point="presim.sim.envs:PointNavEnv", kwargs={"discrete": discrete},
                         vector_entry_point="presim.sim.vector_env:PointNavVectorEnv")


class _GymHook:
    """Meta-path finder that registers the environments once ``gymnasium`` has been imported."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        import importlib.machinery

        sys.meta_path.remove(self)  # find the real spec, once
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        loader = spec.loader
        exec_module = loader.exec_module

        def exec_and_register(module):
            exec_module(module)
            try:
                register_gym_envs()
            except Exception:  # noqa: BLE001 - never break the user's gymnasium import
                pass

        loader.exec_module = exec_and_register
        return spec


import sys  # noqa: E402

if "gymnasium" in sys.modules:
    register_gym_envs()
elif not any(isinstance(f, _GymHook) for f in sys.meta_path):
    sys.meta_path.insert(0, _GymHook())
