"""How well the frame-mode chooser picks between all numba threads and one thread + warp ahead.

Frames between ``threads.SERIAL_MAX_PIXELS`` and ``composite.TILED_MIN_PIXELS`` pixels (e.g.
256x256, 320x240) can render on all numba threads or on one thread with the later views warped
ahead on a helper thread (:mod:`presim.synthesis.warp_ahead`); the images are the same, and a
:class:`presim.synthesis.threads.FrameModeChooser` per camera stream measures which is faster.

This script renders bench_render.py's trajectory (midpoints of consecutive captured views) with
two Renderers, one held to each way, pose by pose in alternating order (``--passes`` passes after
two warm passes), and records each pose's wall times per way and whether the frame had views to
warp ahead. It then replays the chooser offline over the trajectory, cycled for
``--replay-frames`` frames, each frame's time drawn from that pose's recorded times for the way
the chooser picks (frames without views to warp ahead use all threads untimed, as in the
Renderer), and prints the mean ms per frame of: always threads, always ahead, the best way per
pose (an oracle no chooser can beat) and the chooser, with the chooser against the better fixed
way. The replay is deterministic (seeded), so only the recorded times vary from run to run.

    .venv/bin/python benchmarks/bench_frame_modes.py --scene DIR [--sizes 256x256,320x240] [--poses 32]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_render import trajectory  # noqa: E402
import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.store import load_scene  # noqa: E402
from presim.geometry import Intrinsics  # noqa: E402
from presim.synthesis.renderer import RenderConfig, Renderer  # noqa: E402
from presim.synthesis.threads import FrameModeChooser  # noqa: E402

MODES = ("threads", "ahead")


class _Fixed:
    """Stands in for a stream's chooser: always the same way (records nothing)."""

    def __init__(self, mode: str):
        self.mode = mode

    def pick(self) -> str:
        return self.mode

    def record(self, mode: str, wall_ms: float) -> None:
        pass


def record(scene, K: Intrinsics, poses: np.ndarray, passes: int) -> dict:
    """Per pose: wall ms per way, and whether the frame had views to warp ahead."""
    rs = {}
    for m in MODES:
        r = Renderer(scene, RenderConfig())
        r._stream.modes[(K.width, K.height)] = _Fixed(m)  # held to one way (benchmark only)
        for T in list(poses) * 2:  # cold + warm
            r.render(T, K)
        rs[m] = r
    times = {m: [[] for _ in poses] for m in MODES}
    has_jobs = [True] * len(poses)
    for p in range(passes):
        for i, T in enumerate(poses):
            for m in (MODES if (p + i) % 2 == 0 else MODES[::-1]):
                t = time.perf_counter()
                rs[m].render(T, K)
                times[m][i].append((time.perf_counter() - t) * 1e3)
                if m == "ahead":
                    has_jobs[i] = bool(rs[m].last.frame_mode_chosen)
    return {"times": times, "has_jobs": has_jobs}


def replay(rec: dict, frames: int, seed: int = 0) -> dict:
    """Mean ms per frame of the fixed ways, the per-pose oracle and the chooser (offline)."""
    times, has_jobs = rec["times"], rec["has_jobs"]
    P = len(has_jobs)
    mean = {m: np.array([np.mean(t) for t in times[m]]) for m in MODES}
    rng = np.random.default_rng(seed)
    c = FrameModeChooser(MODES)
    total = 0.0
    picks = {m: 0 for m in MODES}
    for f in range(frames):
        i = f % P
        if has_jobs[i]:
            m = c.pick()
        else:
            m = "threads"
        t = times[m][i][rng.integers(len(times[m][i]))]
        if has_jobs[i]:
            c.record(m, t)
        picks[m] += 1
        total += t
    out = {f"always_{m}_ms": float(mean[m].mean()) for m in MODES}
    out["per_pose_best_ms"] = float(np.minimum(mean["threads"], mean["ahead"]).mean())
    out["chooser_ms"] = total / frames
    out["chooser_vs_best_fixed"] = out["chooser_ms"] / min(out["always_threads_ms"], out["always_ahead_ms"])
    out["chooser_picks"] = picks
    out["poses_without_jobs"] = int(P - sum(has_jobs))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True, help="saved scene folder")
    ap.add_argument("--sizes", default="256x256,320x240")
    ap.add_argument("--poses", type=int, default=32, help="trajectory poses")
    ap.add_argument("--passes", type=int, default=6, help="measured passes per way")
    ap.add_argument("--replay-frames", type=int, default=3000)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    if not Path(args.scene).is_dir():
        ap.error(f"--scene {args.scene}: not a folder")
    scene = load_scene(args.scene)
    poses = trajectory(scene, args.poses)
    print(f"scene {args.scene}  poses {len(poses)}  passes {args.passes}  load average {os.getloadavg()}")
    results = {}
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.split("x"))
        K = Intrinsics.from_fov(w, h, scene.intrinsics[0].hfov_deg)
        res = replay(record(scene, K, poses, args.passes), args.replay_frames)
        results[size] = res
        print(f"{size:9s} always threads {res['always_threads_ms']:6.2f} ms  always ahead {res['always_ahead_ms']:6.2f}"
              f"  best per pose {res['per_pose_best_ms']:6.2f}  chooser {res['chooser_ms']:6.2f}"
              f"  = x{res['chooser_vs_best_fixed']:.3f} the better fixed way  picks {res['chooser_picks']}"
              f"  poses without views to warp ahead {res['poses_without_jobs']}")
    if args.json:
        tmp = Path(args.json).with_suffix(".tmp")
        tmp.write_text(json.dumps({"scene": args.scene, "results": results}, indent=1))
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
