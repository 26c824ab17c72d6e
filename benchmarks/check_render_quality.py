"""Image quality of two speed settings of the renderer: ``max_zoom`` and the level of detail.

Sub-commands:

- ``zoom``: quality and speed of ``RenderConfig.max_zoom`` at 1280x720 against exact ray-cast images.
  A 1280x720 camera with the capture's field of view samples the scene ~2x more densely than a
  640x480 capture; ``max_zoom`` caps how much denser than the capture the renderer draws before it
  upsamples. Per value: steady-state ms/frame (median, second pass) and mean PSNR of the delivered
  colour against the exact image at ``--poses`` novel poses (midpoints between captured views).
  Scenes: the analytic synthetic room (exact images from :func:`presim.testing.rect_scene.raycast`)
  and, with ``--sample DIR``, a built-in sample scene folder (exact images from
  :func:`presim.capture.sample_scene.render_ground_truth`).
- ``lod SCENE``: level of detail vs warping every point at reduced target sizes, leave-one-out.
  Targets: every 10th frame from 5; each is rendered from all other frames (``Scene.subset``) at
  its own pose with its intrinsics scaled to W x H, with ``lod_levels=0`` and with the default (3),
  and compared with the real image area-downsampled to W x H (what a W x H camera integrates). The
  scene's refined depth is used when present (refined with all frames, the target included: the same
  for both configurations, so the comparison is fair, the absolute PSNR slightly optimistic).

    python benchmarks/check_render_quality.py zoom [--sample SCENE_DIR] [--zooms 1.0 1.15 1.3]
    NUMBA_NUM_THREADS=1 python benchmarks/check_render_quality.py lod out/apc --sizes 160x120,320x240
    python benchmarks/check_render_quality.py zoom --quick        # smoke run
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two uint8 images."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def _zoom_case(name: str, scene, exact, K, zooms: list[float], n: int) -> dict:
    from presim.synthesis.renderer import RenderConfig, Renderer

    T = scene.T_world_cam
    step = max(1, (len(T) - 1) // n)
    poses = common.trajectory(scene, len(T) - 1)[::step][:n]
    truth = [exact(P, K) for P in poses]
    out = {}
    for z in zooms:
        r = Renderer(scene, RenderConfig(max_zoom=z))
        for P in poses:  # cold pass: prepares every view
            r.render(P, K)
        ms, ps = [], []
        for P, gt in zip(poses, truth):
            wall, _, o = common.timed(lambda: r.render(P, K))
            ms.append(wall)
            ps.append(psnr(o.color, gt))
        r.close()
        out[f"{z:.2f}"] = {"psnr_db_mean": float(np.mean(ps)), "ms_median": common.median(ms)}
        print(f"{name:16s} {K.width}x{K.height}  max_zoom {z:4.2f}  PSNR vs exact {np.mean(ps):6.2f} dB  "
              f"{common.median(ms):7.1f} ms/frame", flush=True)
    return out


def cmd_zoom(args) -> dict:
    from presim.geometry import Intrinsics
    from presim.testing import rect_scene as S

    w, h = common.parse_size(args.size)
    scene, rects = common.synthetic_room()
    res = {"synthetic room": _zoom_case("synthetic room", scene, lambda P, K: S.raycast(rects, P, K)[0],
                                        Intrinsics.from_fov(w, h, 60.0), args.zooms, args.poses)}
    if args.sample:
        from presim.capture.sample_scene import render_ground_truth
        from presim.capture.store import load_scene

        sc = load_scene(args.sample)
        res["sample scene"] = _zoom_case("sample scene", sc, lambda P, K: render_ground_truth(args.sample, P, K)[0],
                                         common.intrinsics_like(sc, w, h), args.zooms, args.poses)
    return res


def cmd_lod(args) -> dict:
    import cv2

    from presim.capture.store import load_scene
    from presim.synthesis.renderer import RenderConfig, Renderer

    scene = load_scene(args.scene)
    n = len(scene)
    out = {}
    for w, h in common.parse_sizes(args.sizes):
        res: dict[int, list[float]] = {0: [], 3: []}
        for t in range(min(5, n - 1), n, 10):
            sub = scene.subset([j for j in range(n) if j != t])
            f = scene.frame(t)
            K = f.K.scaled(w, h)
            gt = cv2.resize(f.color, (w, h), interpolation=cv2.INTER_AREA)
            for lv in res:
                res[lv].append(psnr(Renderer(sub, RenderConfig(lod_levels=lv)).render(f.T_world_cam, K).color, gt))
        out[f"{w}x{h}"] = {"targets": len(res[0]), "psnr_db_lod0": float(np.mean(res[0])),
                           "psnr_db_lod3": float(np.mean(res[3]))}
        print(f"{w}x{h}: targets {len(res[0])}  PSNR lod_levels=0 {np.mean(res[0]):.2f} dB  "
              f"lod_levels=3 {np.mean(res[3]):.2f} dB", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("zoom", help="max_zoom: PSNR against exact images and ms/frame")
    p.add_argument("--sample", help="a sample scene folder (presim sample-scene DIR)")
    p.add_argument("--zooms", type=float, nargs="+", default=[1.0, 1.15, 1.3])
    p.add_argument("--poses", type=int, default=15)
    p.add_argument("--size", default="1280x720", help="target WxH")
    p.add_argument("--quick", action="store_true", help="smoke run: 160x90, 2 poses, zooms 1.0 and 1.3")
    p.add_argument("--json", help="write the results here")
    p = sub.add_parser("lod", help="level of detail vs every point, leave-one-out PSNR")
    p.add_argument("scene", help="saved scene folder")
    p.add_argument("--sizes", default="160x120,320x240")
    p.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    if getattr(args, "quick", False):
        args.size, args.poses, args.zooms = "160x90", 2, [1.0, 1.3]
    common.setup()
    res = cmd_zoom(args) if args.cmd == "zoom" else cmd_lod(args)
    common.write_json(args.json, {"results": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
