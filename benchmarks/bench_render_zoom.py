"""Quality and speed of ``RenderConfig.max_zoom`` at 1280x720 against exact ray-cast images.

A 1280x720 camera with the capture's field of view samples the scene ~2x more densely than a
640x480 capture. ``max_zoom`` caps how much denser than the capture the renderer draws before it
upsamples. For each value: steady-state ms/frame (median, second pass) and mean PSNR of the
delivered color against the exact image at 15 novel poses (midpoints between captured views).

    .venv/bin/python benchmarks/bench_render_zoom.py [--sample SCENE_DIR] [--zooms 1.0 1.15 1.3]

Scenes: the analytic synthetic room (exact images from :func:`presim.testing.rect_scene.raycast`)
and, with ``--sample``, a built-in sample scene folder (exact images from
:func:`presim.capture.sample_scene.render_ground_truth`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.geometry import Intrinsics, make_pose  # noqa: E402
from presim.testing import rect_scene as S  # noqa: E402
from presim.synthesis.renderer import RenderConfig, Renderer  # noqa: E402


def _midpoints(T: np.ndarray, n: int) -> list[np.ndarray]:
    step = max(1, (len(T) - 1) // n)
    return [make_pose(T[i][:3, :3], (T[i][:3, 3] + T[i + 1][:3, 3]) / 2) for i in range(0, len(T) - 1, step)][:n]


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def run(name: str, scene, exact, K: Intrinsics, zooms: list[float], n: int) -> None:
    poses = _midpoints(scene.T_world_cam, n)
    truth = [exact(P, K) for P in poses]
    for z in zooms:
        r = Renderer(scene, RenderConfig(max_zoom=z))
        for P in poses:  # cold pass: prepares every view
            r.render(P, K)
        ms, ps = [], []
        for P, gt in zip(poses, truth):
            t0 = time.perf_counter()
            out = r.render(P, K)
            ms.append((time.perf_counter() - t0) * 1e3)
            ps.append(_psnr(out.color, gt))
        print(f"{name:16s} {K.width}x{K.height}  max_zoom {z:4.2f}  PSNR vs exact {np.mean(ps):6.2f} dB  "
              f"{np.median(ms):7.1f} ms/frame", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", help="a sample scene folder (presim sample-scene DIR)")
    ap.add_argument("--zooms", type=float, nargs="+", default=[1.0, 1.15, 1.3])
    ap.add_argument("--poses", type=int, default=15)
    args = ap.parse_args()
    K_cap = Intrinsics.from_fov(640, 480, 60.0)
    rects = S.room_rects()
    scene = S.make_scene(rects, S.orbit_poses(16, span_m=1.6), K_cap)
    run("synthetic room", scene, lambda P, K: S.raycast(rects, P, K)[0], Intrinsics.from_fov(1280, 720, 60.0),
        args.zooms, args.poses)
    if args.sample:
        from presim.capture.sample_scene import render_ground_truth
        from presim.capture.store import load_scene

        sc = load_scene(args.sample)
        K = Intrinsics.from_fov(1280, 720, sc.intrinsics[0].hfov_deg)
        run("sample scene", sc, lambda P, K: render_ground_truth(args.sample, P, K)[0], K, args.zooms, args.poses)
    return 0


if __name__ == "__main__":
    sys.exit(main())
