"""What the functions of a frame cost inside the render loop against the same call repeated alone.

Wraps the main per-frame functions of the synthesis path with timers, renders a trajectory of
novel poses (``bench_render.trajectory``: midpoints of consecutive captured views) at one size in
steady state, and prints per function its calls per frame, the mean µs per call inside frames, and
the same calls on their own, warm in the caches: every call of one extra pass over the trajectory
is kept (its array arguments copied) and repeated ``--repeats`` times alone; their medians are
averaged. Their ratio is what running between the frame's kernels
costs a call: the kernels stream about 1 MB per view through the L2, so the small numpy, LAPACK and
OpenCV calls between them start cold (docs/synthesis.md, "Cold calls inside frames").

    PYTHONPATH=. .venv/bin/python benchmarks/bench_frame_calls.py --scene /work/scenes/apc --size 128x128
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)

# (module, attribute, label): looked up where the render loop calls them
TARGETS = (
    ("presim.synthesis.renderer", "check_rigid", "check_rigid"),
    ("presim.synthesis.renderer.Renderer", "select", "Renderer.select"),
    ("presim.synthesis.grids.FrameGrids", "next_view", "FrameGrids.next_view"),
    ("presim.synthesis.core", "analyse_hole_mask", "analyse_hole_mask"),
    ("presim.synthesis.core", "merge_into_holes", "merge_into_holes"),
    ("presim.synthesis.core", "warp_layers", "warp_layers"),
    ("presim.synthesis.core", "filtered_composite_banded", "filtered_composite_banded"),
    ("presim.synthesis.core", "fill_holes", "fill_holes"),
)


def _resolve(path: str):
    import importlib

    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for p in parts[k:]:
            obj = getattr(obj, p)
        return obj
    raise ImportError(path)


def _copied(x):
    """``x`` with its numpy arrays copied (in tuples, lists and dicts too); other objects as they are."""
    import numpy as np

    if isinstance(x, np.ndarray):
        return x.copy()
    if isinstance(x, (tuple, list)):
        return type(x)(_copied(v) for v in x)
    if isinstance(x, dict):
        return {key: _copied(v) for key, v in x.items()}
    return x


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", help="saved scene folder (default: the sample scene, seed 0, 30 frames, built once "
                                    "into the temp directory as benchmarks/bench_pointnav.py does)")
    ap.add_argument("--size", default="128x128", help="target size WxH")
    ap.add_argument("--frames", type=int, default=16, help="trajectory poses per pass")
    ap.add_argument("--passes", type=int, default=10, help="measured passes over the trajectory")
    ap.add_argument("--repeats", type=int, default=20, help="repeats of each captured call alone (median)")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    W, H = (int(v) for v in args.size.lower().split("x"))

    from bench_pointnav import load_sim_scene
    from bench_render import in_memory, trajectory

    from presim.geometry import Intrinsics
    from presim.synthesis.renderer import RenderConfig, Renderer

    args.scene, scene = load_sim_scene(args.scene)
    scene = in_memory(scene)
    K = Intrinsics.from_fov(W, H, scene.intrinsics[0].hfov_deg)
    total: dict[str, float] = {}
    calls: dict[str, int] = {}
    last: dict[str, tuple] = {}
    mode = ["off"]  # "time": measured frames; "capture": keep one call's arguments per function

    def wrap(owner, name: str, label: str) -> None:
        fn = getattr(owner, name)

        def timed(*a, **k):
            if mode[0] == "capture":
                last.setdefault(label, []).append((fn, _copied(a), _copied(k)))
            if mode[0] != "time":
                return fn(*a, **k)
            t = time.perf_counter()
            out = fn(*a, **k)
            total[label] = total.get(label, 0.0) + time.perf_counter() - t
            calls[label] = calls.get(label, 0) + 1
            return out

        setattr(owner, name, timed)

    for path, attr, label in TARGETS:
        wrap(_resolve(path), attr, label)
    r = Renderer(scene, RenderConfig())
    poses = trajectory(scene, args.frames)
    for _ in range(3):  # views prepared, kernels compiled, choosers settled
        for T in poses:
            r.render(T, K)
    n = 0
    mode[0] = "time"
    t0 = time.perf_counter()
    for _ in range(args.passes):
        for T in poses:
            r.render(T, K)
            n += 1
    frame_ms = (time.perf_counter() - t0) / n * 1e3
    mode[0] = "capture"  # one more pass keeps each function's first call's arguments (copied)
    for T in poses:
        r.render(T, K)
    mode[0] = "off"
    print(f"scene {args.scene}  {W}x{H}  {n} frames  {frame_ms:.3f} ms per frame (with the timers)")
    print(f"{'function':28s} {'calls/frame':>11s} {'in frames us':>13s} {'alone us':>9s} {'ratio':>6s}")
    res = {}
    for label in (t[2] for t in TARGETS):
        if label not in calls:
            continue
        alone_each = []
        for fn, a, k in last[label]:  # every call of the capture pass, each repeated alone
            hot = []
            for _ in range(args.repeats):
                a2, k2 = _copied(a), _copied(k)  # (a call may write into its array arguments)
                t = time.perf_counter()
                fn(*a2, **k2)
                hot.append(time.perf_counter() - t)
            alone_each.append(statistics.median(hot))
        inside = total[label] / calls[label] * 1e6
        alone = statistics.fmean(alone_each) * 1e6
        res[label] = {"calls_per_frame": calls[label] / n, "us_in_frames": inside, "us_alone": alone}
        print(f"{label:28s} {calls[label] / n:11.2f} {inside:13.1f} {alone:9.1f} {inside / alone:6.2f}")
    if args.json:
        args.json.write_text(json.dumps({"scene": args.scene, "size": [W, H], "frame_ms": frame_ms,
                                         "results": res}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
