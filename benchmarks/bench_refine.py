"""Benchmark of the depth refinement (thesis §3.4.1).

Prints the median wall time of ``refine_depth`` (numba) on one 640x480 frame with 10 reference views,
per-pixel throughput against the plain reference implementation measured in the same run (on a small
crop, since it is ~1000x slower), and the guided / median filter baselines at full size.

    .venv/bin/python benchmarks/bench_refine.py [--scene SCENE] [--repeats 3]

Without ``--scene`` an analytic two-plane scene is used.

Accuracy mode (after ``presim refine SCENE``), against a clean ground-truth depth (N, H, W) .npy:

    .venv/bin/python benchmarks/bench_refine.py --accuracy SCENE SCENE/ground_truth/depth_clean.npy

prints the mean absolute error of raw / refined / guided-filtered / median-filtered depth on pixels
valid in both (raw and output), the error of filled pixels and the coverage.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (numba compilation / caches)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def accuracy(scene_dir: str, gt_path: str) -> None:
    from presim.capture.store import load_scene
    from presim.depth.filters import guided_filter_depth, median_filter_depth

    sc = load_scene(scene_dir)
    if sc.depth_refined is None:
        raise SystemExit(f"{scene_dir}: no depth_refined.npy; run `presim refine {scene_dir}` first")
    gt = np.load(gt_path, mmap_mode="r")
    names = ("raw", "refined", "guided", "median")
    acc = {n: {"abs_both": 0.0, "n_both": 0, "abs_fill": 0.0, "n_fill": 0, "n_cov": 0, "gross_both": 0,
               "edge_px": []} for n in names}
    n_gt = 0
    for i in range(len(sc)):
        f = sc.frame(i)
        raw, g = f.depth_m, np.asarray(gt[i])
        outs = {"raw": raw, "refined": np.asarray(sc.depth_refined[i]),
                "guided": guided_filter_depth(f.color, raw), "median": median_filter_depth(raw)}
        has_gt = g > 0
        n_gt += int(has_gt.sum())
        for n, d in outs.items():
            both = (raw > 0) & (d > 0) & has_gt
            fill = (raw == 0) & (d > 0) & has_gt
            e = np.abs(d - g)
            a = acc[n]
            a["abs_both"] += float(e[both].sum())
            a["n_both"] += int(both.sum())
            a["gross_both"] += int((e[both] > 0.05).sum())
            a["abs_fill"] += float(e[fill].sum())
            a["n_fill"] += int(fill.sum())
            a["n_cov"] += int(((d > 0) & has_gt).sum())
            a["edge_px"].append(edge_misalignment_px(d, g))
    print(f"{scene_dir}: {len(sc)} frames, errors vs {gt_path}")
    print("| depth | MAE valid-in-both mm | >5 cm % | filled-pixel MAE mm | filled % of GT px | coverage % | edge misalignment px |")
    print("|---|---|---|---|---|---|---|")
    for n in names:
        a = acc[n]
        mae = 1e3 * a["abs_both"] / max(a["n_both"], 1)
        fmae = 1e3 * a["abs_fill"] / a["n_fill"] if a["n_fill"] else float("nan")
        print(f"| {n} | {mae:.2f} | {100 * a['gross_both'] / max(a['n_both'], 1):.2f} | {fmae:.1f} | "
              f"{100 * a['n_fill'] / n_gt:.2f} | {100 * a['n_cov'] / n_gt:.2f} | {np.nanmean(a['edge_px']):.2f} |")
    r = acc["raw"]["abs_both"] / acc["raw"]["n_both"]
    f = acc["refined"]["abs_both"] / acc["refined"]["n_both"]
    print(f"refined vs raw MAE (valid in both): {100 * (1 - f / r):.1f} % lower")


def depth_edges(depth_m: np.ndarray, rel_jump: float = 0.05) -> np.ndarray:
    """Pixels next to a depth jump larger than ``rel_jump`` of the depth (or next to missing depth)."""
    d = depth_m.astype(np.float32)
    e = np.zeros(d.shape, bool)
    for a, b in ((d[:, 1:], d[:, :-1]), (d[1:, :], d[:-1, :])):
        jump = (np.abs(a - b) > rel_jump * np.maximum(a, b)) & (a > 0) & (b > 0)
        if a.shape[1] != d.shape[1]:
            e[:, 1:] |= jump
            e[:, :-1] |= jump
        else:
            e[1:, :] |= jump
            e[:-1, :] |= jump
    return e


def edge_misalignment_px(depth_m: np.ndarray, gt_m: np.ndarray, cap_px: float = 5.0) -> float:
    """Mean distance (px) of the depth edges of ``depth_m`` to the nearest true depth edge, each
    distance capped at ``cap_px`` (a truncated chamfer distance: a spurious edge far inside a surface
    counts as ``cap_px``, not as hundreds of pixels). NaN for frames with no true depth edge."""
    import cv2

    gt_e = depth_edges(gt_m)
    if not gt_e.any():
        return float("nan")
    dist = cv2.distanceTransform((~gt_e).astype(np.uint8), cv2.DIST_L2, 3)
    e = depth_edges(depth_m)
    e &= gt_m > 0  # edges of the sensor's missing-depth regions are not misalignment
    return float(np.minimum(dist[e], cap_px).mean()) if e.any() else float("nan")


def figure(scene_dir: str, gt_path: str, out: str, frame: int, box: tuple[int, int, int, int]) -> None:
    """Crop of a color image with raw (left) and refined (right) depth edges in magenta and the
    true depth edges in green."""
    import cv2

    from presim.capture.store import load_scene
    from presim.io_utils import write_png

    sc = load_scene(scene_dir)
    gt = np.asarray(np.load(gt_path, mmap_mode="r")[frame])
    f = sc.frame(frame)
    if box is None:  # the 240x180 window with the most true depth edges
        import cv2 as _cv

        dens = _cv.boxFilter(depth_edges(gt).astype(np.float32), -1, (240, 180), normalize=False,
                             anchor=(0, 0), borderType=_cv.BORDER_CONSTANT)
        dens[gt.shape[0] - 180:, :] = -1
        dens[:, gt.shape[1] - 240:] = -1
        yy, xx = np.unravel_index(int(np.argmax(dens)), dens.shape)
        box = (int(xx), int(yy), 240, 180)
    x, y, w, h = box
    panels = []
    for d, name in ((f.depth_m, "raw"), (np.asarray(sc.depth_refined[frame]), "refined")):
        img = f.color.copy()
        img[depth_edges(gt)] = (0, 255, 0)
        img[depth_edges(d)] = (255, 0, 255)
        crop = cv2.resize(img[y:y + h, x:x + w], (3 * w, 3 * h), interpolation=cv2.INTER_NEAREST)
        cv2.putText(crop, f"{name}: {edge_misalignment_px(d, gt):.2f} px", (8, 28), cv2.FONT_HERSHEY_SIMPLEX,
                    0.9, (255, 255, 255), 2)
        panels.append(crop)
    write_png(out, np.concatenate([panels[0], np.full((3 * h, 6, 3), 255, np.uint8), panels[1]], axis=1))
    print(f"wrote {out}")


def main() -> None:
    from presim.depth.filters import guided_filter_depth, median_filter_depth
    from presim.depth.refine import RefineConfig, RefView, refine_depth, select_reference_views
    from presim.testing.two_planes import render_two_planes, two_plane_poses
    from presim.geometry import Intrinsics

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=None, help="saved scene (default: analytic two-plane scene)")
    ap.add_argument("--frame", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--accuracy", nargs=2, metavar=("SCENE", "GT_DEPTH_NPY"), default=None,
                    help="accuracy of SCENE/depth_refined.npy against a clean depth .npy")
    ap.add_argument("--figure", nargs=3, metavar=("SCENE", "GT_DEPTH_NPY", "OUT_PNG"), default=None,
                    help="write the edge-alignment figure (raw vs refined depth edges) for --frame")
    ap.add_argument("--box", type=int, nargs=4, default=None, metavar=("X", "Y", "W", "H"),
                    help="crop of the figure, pixels (default: the window with the most true depth edges)")
    args = ap.parse_args()
    if args.accuracy:
        accuracy(*args.accuracy)
        return
    if args.figure:
        figure(args.figure[0], args.figure[1], args.figure[2], args.frame, None if args.box is None else tuple(args.box))
        return

    if args.scene:
        from presim.capture.store import load_scene

        sc = load_scene(args.scene)
        i = min(args.frame, len(sc) - 1)
        f = sc.frame(i)
        color, depth, K, T = f.color, f.depth_m, f.K, f.T_world_cam
        refs = [RefView(*sc.frames.load(j), sc.intrinsics[j], sc.T_world_cam[j])
                for j in select_reference_views(sc.T_world_cam, i, range(len(sc)))]
    else:
        K = Intrinsics.from_fov(640, 480, 60.0)
        poses = two_plane_poses(11, 0.06)
        views = [render_two_planes(P, K) for P in poses]
        color, depth = views[0]
        depth = depth.copy()
        depth[200:260, 100:180] = 0
        T = poses[0]
        refs = [RefView(c, d, K, P) for (c, d), P in zip(views[1:], poses[1:])]
    H, W = depth.shape
    t_fast = _time(lambda: refine_depth(color, depth, K, T, refs), args.repeats)
    t_gf = _time(lambda: guided_filter_depth(color, depth), args.repeats)
    t_med = _time(lambda: median_filter_depth(depth), args.repeats)

    # Same algorithm, plain reference vs numba, on a 40x30 crop (the reference is too slow for more).
    h, w = 30, 40
    Kc = Intrinsics(K.fx, K.fy, K.cx - (W // 2 - w // 2), K.cy - (H // 2 - h // 2), w, h)
    crop = (slice(H // 2 - h // 2, H // 2 - h // 2 + h), slice(W // 2 - w // 2, W // 2 - w // 2 + w))
    # References cropped the same way (their intrinsics shifted), so that preparing full-size
    # reference images does not dominate the tiny crop's time.
    refs_c = [RefView(np.ascontiguousarray(r.color[crop]), np.ascontiguousarray(r.depth_m[crop]),
                      Intrinsics(r.K.fx, r.K.fy, r.K.cx - (W // 2 - w // 2), r.K.cy - (H // 2 - h // 2), w, h),
                      r.T_world_cam) for r in refs]
    args_c = (np.ascontiguousarray(color[crop]), np.ascontiguousarray(depth[crop]), Kc, T, refs_c)
    t_ref_c = _time(lambda: refine_depth(*args_c, config=RefineConfig(backend="reference")), 1)
    t_fast_c = _time(lambda: refine_depth(*args_c), args.repeats)

    print(f"refine_depth numba, {W}x{H}, {len(refs)} refs: {1e3 * t_fast:.0f} ms/frame (median of {args.repeats})")
    print(f"guided filter baseline: {1e3 * t_gf:.1f} ms   median filter baseline: {1e3 * t_med:.1f} ms")
    print(f"{w}x{h} crop: reference {1e3 * t_ref_c:.0f} ms, numba {1e3 * t_fast_c:.2f} ms "
          f"-> numba is {t_ref_c / t_fast_c:.0f}x faster")


if __name__ == "__main__":
    main()
