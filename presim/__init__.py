"""PreSim: a photo-realistic RGB-D simulator for robots, built from captured RGB-D images.

Data flow (one sub-package per stage)::

    capture -> align / photometric / depth -> synthesis -> sensors -> sim -> outputs -> datasets -> pose

``import presim`` changes nothing in the process (no environment variables, allocator settings,
warning filters or import hooks). The process settings the renderer's speed depends on are applied
by :func:`presim.runtime.configure`, which the ``presim`` command line and the Gymnasium
environments call; a library user calls it once, first thing (docs/layout.md, "Process settings").
The Gymnasium ids are registered by ``import presim.sim.envs`` (or ``gym.make("presim.sim.envs:
PreSim-PointNav-v0", ...)``, which imports it).
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
