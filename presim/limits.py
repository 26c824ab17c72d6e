"""Input checks and memory limits, applied before any work starts.

Two kinds of refusal, both a :class:`InputError` (a ``ValueError``, so the CLI prints one line)
whose message starts with the flag (or argument) it is about:

- **invalid values**: :func:`check_positive`, :func:`check_intrinsics` refuse ``0``, negative and
  non-finite sizes, focal lengths and rates, naming the flag;
- **memory**: every command that allocates from user-given sizes estimates its peak memory from
  them (:func:`render_memory_bytes`, :func:`sample_scene_memory_bytes`, ...) and
  :func:`check_memory` refuses when the estimate exceeds the budget, naming the flag, the estimate
  and the limit. The budget is ``DEFAULT_MEMORY_FRACTION`` of the memory available when the command
  starts (``MemAvailable`` of ``/proc/meminfo``), raised or lowered with ``--max-memory SIZE``
  (e.g. ``64G``) or the ``PRESIM_MAX_MEMORY`` environment variable.

The estimates are upper bounds: they count the address space of the large arrays the code
allocates per frame (numpy's ``np.empty`` reserves it even where pages are never touched, and an
allocation past what the kernel will overcommit fails), so the measured peak RSS is lower (on the
toy room at 1600x1200, 4 layers: +54 MB RSS over a 160x120 render; the estimate is 292 MB). They do
not include the fixed cost of the interpreter and libraries (~0.2-0.6 GB). docs/limits.md.
"""

from __future__ import annotations

import math
import os
import re

from presim.io_utils import format_size, free_disk_bytes

__all__ = ["InputError", "MemoryLimitError", "DEFAULT_MEMORY_FRACTION", "parse_size", "format_size",
           "available_memory_bytes", "memory_budget_bytes", "check_memory", "check_positive",
           "check_positive_int", "check_intrinsics", "render_memory_bytes", "sample_scene_memory_bytes",
           "gen_bop_memory_bytes", "check_render_memory", "GEN_BOP_BYTES_PER_PX", "GEN_BOP_RECORD_BYTES",
           "gen_bop_output_bytes", "check_disk"]

DEFAULT_MEMORY_FRACTION = 0.5
"""Share of the available memory a command may plan to use without ``--max-memory``."""

# Bytes per output pixel of one synthesized frame: the layered warp of one view (float32 depth +
# rgb8 per layer, plus the crack-filtered copy) and the per-pixel working images (accumulators,
# source ids, hole analysis, fill, the outputs).
_WARP_BYTES_PER_PX_LAYER = 2 * (4 + 3)
_FRAME_BYTES_PER_PX = 96


class InputError(ValueError):
    """A value the user gave (a flag, an argument, a message field) that cannot be used."""

    def __init__(self, flag: str, problem: str):
        self.flag, self.problem = flag, problem
        super().__init__(f"{flag}: {problem}")


class MemoryLimitError(InputError):
    """The memory a command would need from its arguments exceeds the budget."""


# ---- sizes ------------------------------------------------------------------------------------

_UNITS = {"": 1, "B": 1, "K": 2**10, "KB": 2**10, "KIB": 2**10, "M": 2**20, "MB": 2**20, "MIB": 2**20,
          "G": 2**30, "GB": 2**30, "GIB": 2**30, "T": 2**40, "TB": 2**40, "TIB": 2**40}


def parse_size(text: str | int | float, flag: str = "--max-memory") -> int:
    """``'64G'``, ``'512M'``, ``'1.5GiB'``, ``'2000000'`` (bytes) -> bytes (binary units)."""
    if isinstance(text, (int, float)):
        value, unit = float(text), ""
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*", str(text))
        if not m or m.group(2).upper() not in _UNITS:
            raise InputError(flag, f"expected a size like 8G, 512M or a number of bytes, got {text!r}")
        value, unit = float(m.group(1)), m.group(2).upper()
    if not math.isfinite(value) or value <= 0:
        raise InputError(flag, f"must be a positive size, got {text!r}")
    return int(value * _UNITS[unit])


def available_memory_bytes() -> int:
    """Memory available to new allocations now (``MemAvailable``; total RAM where unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def memory_budget_bytes(max_memory: str | int | float | None = None) -> int:
    """The budget: ``max_memory`` when given, else ``$PRESIM_MAX_MEMORY``, else
    ``DEFAULT_MEMORY_FRACTION`` of :func:`available_memory_bytes`."""
    if max_memory is not None:
        return parse_size(max_memory)
    env = os.environ.get("PRESIM_MAX_MEMORY")
    if env:
        return parse_size(env, "PRESIM_MAX_MEMORY")
    return int(DEFAULT_MEMORY_FRACTION * available_memory_bytes())


def check_memory(estimate_bytes: float, flag: str, what: str, max_memory: str | int | float | None = None) -> int:
    """Refuse (``MemoryLimitError`` naming ``flag``) when ``estimate_bytes`` is over the budget;
    returns the budget."""
    budget = memory_budget_bytes(max_memory)
    if not math.isfinite(estimate_bytes) or estimate_bytes > budget:
        src = "--max-memory" if max_memory is not None else (
            "PRESIM_MAX_MEMORY" if os.environ.get("PRESIM_MAX_MEMORY") else
            f"{DEFAULT_MEMORY_FRACTION:.0%} of the available memory")
        raise MemoryLimitError(flag, f"{what} needs an estimated {format_size(estimate_bytes)}, over the limit of "
                                     f"{format_size(budget)} ({src}; raise it with --max-memory SIZE)")
    return budget


# ---- values -----------------------------------------------------------------------------------

def check_positive(value, flag: str, allow_none: bool = True):
    """A finite number > 0 (None passes when ``allow_none``)."""
    if value is None and allow_none:
        return value
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(flag, f"must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(flag, f"must be a positive finite number, got {value!r}")
    return value


def check_positive_int(value, flag: str, allow_none: bool = True):
    """An integer >= 1 (None passes when ``allow_none``)."""
    if value is None and allow_none:
        return value
    if isinstance(value, bool) or not isinstance(value, (int,)) and not (
            isinstance(value, float) and value.is_integer()):
        raise InputError(flag, f"must be a whole number, got {value!r}")
    if value < 1:
        raise InputError(flag, f"must be at least 1, got {value!r}")
    return int(value)


def check_intrinsics(width=None, height=None, fx=None, fy=None, cx=None, cy=None, prefix: str = "--") -> None:
    """Image size and pinhole values as flags: sizes >= 1, focal lengths > 0, principal point
    finite (None = not given). Flags are named ``{prefix}width`` etc."""
    check_positive_int(width, f"{prefix}width")
    check_positive_int(height, f"{prefix}height")
    check_positive(fx, f"{prefix}fx")
    check_positive(fy, f"{prefix}fy")
    for name, v in (("cx", cx), ("cy", cy)):
        if v is not None and not math.isfinite(float(v)):
            raise InputError(f"{prefix}{name}", f"must be a finite number, got {v!r}")


# ---- estimates --------------------------------------------------------------------------------

def render_memory_bytes(width: int, height: int, num_layers: int = 4) -> float:
    """Peak bytes of synthesizing one ``width x height`` frame with ``num_layers`` layers."""
    px = float(width) * float(height)
    return px * (_WARP_BYTES_PER_PX_LAYER * float(num_layers) + _FRAME_BYTES_PER_PX)


def sample_scene_memory_bytes(width: int, height: int, frames: int) -> float:
    """Peak bytes of building the sample scene: every frame's color, raw and exact depth, masks and
    the ray-cast buffers are held until saved (~40 B/px/frame) plus one frame of ray casting."""
    px = float(width) * float(height)
    return px * 40.0 * float(frames) + px * 200.0


def gen_bop_memory_bytes(width: int, height: int, workers: int = 1, num_layers: int = 4) -> float:
    """Peak bytes of ``gen-bop``: each worker synthesizes and annotates one frame at a time
    (a frame plus per-object depth/mask images, ~32 B/px)."""
    return float(max(1, workers)) * (render_memory_bytes(width, height, num_layers) + 32.0 * width * height)


def check_render_memory(width: int, height: int, num_layers: int = 4, max_memory=None,
                        what: str = "rendering one frame", size_flag: str = "--width/--height",
                        layers_flag: str = "--layers", per_frame_extra_px_bytes: float = 0.0,
                        copies: int = 1) -> int:
    """:func:`check_memory` for synthesized frames, blaming ``layers_flag`` when the size alone would
    fit with the default 4 layers and the layer count is what breaks the budget, else ``size_flag``."""
    px = float(width) * float(height)
    est = copies * (render_memory_bytes(width, height, num_layers) + per_frame_extra_px_bytes * px)
    budget = memory_budget_bytes(max_memory)
    if est <= budget:
        return budget
    base = copies * (render_memory_bytes(width, height, min(num_layers, 4)) + per_frame_extra_px_bytes * px)
    flag = layers_flag if (num_layers > 4 and base <= budget) else size_flag
    shown = f"{flag} ({width}x{height}, {num_layers} layers)"
    return check_memory(est, shown, what, max_memory)


# ---- disk -------------------------------------------------------------------------------------

GEN_BOP_BYTES_PER_PX = 1.0
"""Bytes ``gen-bop`` writes per image pixel (color PNG + 16-bit depth PNG + two masks per object,
all compressed). A low estimate, so that only jobs that cannot fit are refused: measured 1.65 B/px
(sample scene) and 1.79 B/px (toy room) at 320x240; real captures compress worse (docs/limits.md)."""
GEN_BOP_RECORD_BYTES = 4096
"""Memory per image slot held until ``gen-bop`` writes the scene's JSON files (frame records)."""


def gen_bop_output_bytes(width: int, height: int, frames: int) -> float:
    """Estimated bytes of the images ``gen-bop`` writes (a low estimate; see GEN_BOP_BYTES_PER_PX)."""
    return float(frames) * float(width) * float(height) * GEN_BOP_BYTES_PER_PX


def check_disk(estimate_bytes: float, path, flag: str, what: str) -> None:
    """Refuse (``InputError`` naming ``flag``) when ``estimate_bytes`` is more than the free space of
    the file system that will hold ``path`` (or its nearest existing parent)."""
    free = free_disk_bytes(path)
    if not math.isfinite(estimate_bytes) or estimate_bytes > free:
        raise InputError(flag, f"{what} needs an estimated {format_size(estimate_bytes)} of disk, more than the "
                               f"{format_size(free)} free at {path}")
