"""What the benchmark scripts share: scenes, trajectories, timing and JSON output.

Every script in this folder starts the same way, so that it imports the ``presim`` of its own tree
(``bench_ab.py`` relies on that when it runs two trees side by side)::

    ROOT = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(ROOT))
    from benchmarks import common  # noqa: E402

then parses its arguments (``--help`` stays fast: nothing heavy is imported before) and calls
:func:`setup` before it imports torch or runs a kernel (``presim.runtime.configure``: the process
settings the timings depend on).

Scenes (no machine paths: the real captures are found at ``../shared/data`` relative to the
repository root, the sample scene is built once into a cache folder under the temp directory):

- :func:`sample_scene` — the built-in sample scene (a room with a floor; seed, size and frame count
  name the cache folder);
- :func:`apc_capture` — ``apc_cardboard_bin_kinfu50`` read by the kinfu importer (raw depth);
- :func:`synthetic_room` — the analytic room of :mod:`presim.testing.rect_scene` (no files);
- :func:`load_saved` — a saved scene folder, or the sample scene when none is given.

Timing: warm up, repeat, report medians; a ratio is always against a baseline measured in the same
run, the measured configurations alternating (:func:`alternate`) so load changes on a shared machine
hit both.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
"""The repository root of this tree."""
DATA = ROOT.parent / "shared" / "data"
"""Real captures (read only): ``../shared/data`` relative to the repository root."""
APC = DATA / "apc_cardboard_bin_kinfu50"
LMO = DATA / "lmo_scene000002"
CACHE = Path(tempfile.gettempdir()) / "presim_bench"
"""Scenes the benchmarks build once (the sample scene at each size) live here."""


# ---- process ---------------------------------------------------------------------------------

def setup(progress: bool = False) -> None:
    """``presim.runtime.configure()`` (the process settings timings depend on) and, unless
    ``progress``, no progress bars. Call it after parsing the arguments, before any kernel runs."""
    if not progress:
        os.environ.setdefault("PRESIM_NO_PROGRESS", "1")
    import presim.runtime

    presim.runtime.configure()


def header(**extra: Any) -> str:
    """One line with what the numbers depend on: numba threads, CPUs, load average, ``extra``."""
    try:
        import numba

        threads = numba.get_num_threads()
    except ImportError:  # pragma: no cover - numba is a dependency
        threads = None
    parts = [f"{k} {v}" for k, v in extra.items()]
    parts += [f"numba threads {threads}", f"cpus {os.cpu_count()}", f"load average {os.getloadavg()}"]
    line = "  ".join(parts)
    print(line, flush=True)
    return line


def status_mb(key: str, pid: int | str = "self") -> float:
    """A ``/proc/PID/status`` memory figure (``VmRSS``, ``VmHWM``, ``RssAnon``) in MiB (NaN if absent)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_json(path: str | Path | None, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (temp file + rename); nothing when None."""
    if not path:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
    os.replace(tmp, path)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


# ---- arguments -------------------------------------------------------------------------------

def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` -> ``(640, 480)``; a clear error otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"size {text!r}: expected WxH, e.g. 640x480") from None
    if w < 1 or h < 1:
        raise SystemExit(f"size {text!r}: width and height must be >= 1")
    return w, h


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """``"640x480,128x128"`` -> ``[(640, 480), (128, 128)]``."""
    return [parse_size(s) for s in text.split(",") if s]


# ---- scenes ----------------------------------------------------------------------------------

def sample_scene(frames: int = 30, width: int = 640, height: int = 480, seed: int = 0) -> Path:
    """Folder of the built-in sample scene with these settings, built once into :data:`CACHE`
    (built into a temporary sibling and renamed, so an interrupted build leaves nothing half-made)."""
    import shutil

    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    dst = CACHE / f"sample_seed{seed}_{width}x{height}_{frames}"
    if (dst / "scene.json").is_file():
        return dst
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=dst.name + ".", dir=CACHE))
    try:
        print(f"building the sample scene into {dst} (once) ...", file=sys.stderr, flush=True)
        build_sample_scene(tmp / "scene", seed=seed, overwrite=True,
                           config=SampleSceneConfig(width=width, height=height, num_frames=frames))
        try:
            os.replace(tmp / "scene", dst)
        except OSError:  # another process built it meanwhile
            if not (dst / "scene.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dst


def load_saved(path: str | Path | None, frames: int = 30):
    """``(folder, Scene)``: the saved scene at ``path``, or (None) the sample scene of ``frames``
    frames at 640x480 (:func:`sample_scene`)."""
    from presim.capture.store import load_scene

    folder = Path(path) if path else sample_scene(frames)
    if not (folder / "scene.json").is_file():
        raise SystemExit(f"{folder}: not a saved scene (no scene.json)")
    return str(folder), load_scene(folder)


def in_memory(scene):
    """The scene with all frames decoded into arrays (PNG decoding is not what a benchmark times)."""
    import dataclasses

    from presim.capture.scene import ArrayFrameSource

    cols, deps = zip(*(scene.frames.load(i) for i in range(len(scene))))
    return dataclasses.replace(scene, frames=ArrayFrameSource(np.stack(cols), np.stack(deps)))


def apc_capture(decoded: bool = True):
    """The APC capture (``../shared/data/apc_cardboard_bin_kinfu50``, kinfu importer, raw depth),
    decoded into memory unless ``decoded=False``; None (with a note) when the data is absent."""
    if not APC.is_dir():
        print(f"note: {APC} not found, the apc capture is skipped", file=sys.stderr)
        return None
    from presim.capture.importers.kinfu import read

    scene = read(APC)
    return in_memory(scene) if decoded else scene


def synthetic_room(width: int = 640, height: int = 480, views: int = 16):
    """The analytic room (:mod:`presim.testing.rect_scene`) seen by ``views`` orbiting cameras,
    plus its rectangles (for exact ray-cast images): ``(scene, rects)``."""
    from presim.geometry import Intrinsics
    from presim.testing import rect_scene as S

    rects = S.room_rects()
    return S.make_scene(rects, S.orbit_poses(views, span_m=1.6), Intrinsics.from_fov(width, height, 60.0)), rects


def trajectory(scene, n: int) -> np.ndarray:
    """``n`` novel poses (N, 4, 4): midpoints of consecutive captured views (cycled), each with the
    rotation of the first of its pair. Every frame is a new pose near the capture."""
    from presim.geometry import make_pose

    T = scene.T_world_cam
    if len(T) < 2:
        raise SystemExit("a trajectory needs a scene with at least 2 frames")
    out = []
    for k in range(n):
        i = k % (len(T) - 1)
        out.append(make_pose(T[i][:3, :3], (T[i][:3, 3] + T[i + 1][:3, 3]) / 2))
    return np.stack(out)


def intrinsics_like(scene, width: int, height: int):
    """A ``width`` x ``height`` camera with the horizontal field of view of the scene's first frame."""
    from presim.geometry import Intrinsics

    return Intrinsics.from_fov(width, height, scene.intrinsics[0].hfov_deg)


# ---- timing ----------------------------------------------------------------------------------

def timed(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """``(wall ms, CPU ms, result)`` of one call; CPU = process time summed over all threads."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3, out


def median_ms(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> tuple[float, Any]:
    """``(median wall ms over repeats, last result)`` after ``warmup`` untimed calls."""
    out = None
    for _ in range(warmup):
        out = fn()
    ts = []
    for _ in range(max(1, repeats)):
        ms, _, out = timed(fn)
        ts.append(ms)
    return statistics.median(ts), out


def alternate(runs: dict[str, Callable[[], Any]], repeats: int) -> dict[str, list[tuple[float, float]]]:
    """Calls every function of ``runs`` once per repeat, in ABBA order (A B, B A, A B, ...: a linear
    drift of the machine's speed hits all alike); returns per name its ``(wall ms, CPU ms)`` list."""
    names = list(runs)
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in names}
    for rep in range(repeats):
        for k in (names if rep % 2 == 0 else names[::-1]):
            wall, cpu, _ = timed(runs[k])
            out[k].append((wall, cpu))
    return out


def median(values: Iterable[float]) -> float:
    """Median as a float (NaN for no values)."""
    v = list(values)
    return float(statistics.median(v)) if v else float("nan")


def ratio(base: float, new: float) -> float:
    """``base / new`` (> 1: new is faster when both are times); NaN when ``new`` is 0."""
    return base / new if new else float("nan")
