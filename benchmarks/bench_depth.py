"""Depth costs and accuracy: the multi-view refinement (thesis §3.4.1) and alignment + fusion (§5.3.4).

Sub-commands:

- ``refine``: median wall time of ``refine_depth`` (numba) on one frame with 10 reference views
  against the guided / median filter baselines at full size, and per-pixel throughput against the
  plain reference implementation measured in the same run (on a 40x30 crop: it is ~1000x slower).
  Without ``--scene``: an analytic two-plane scene at 640x480 (``--size``).
- ``accuracy SCENE GT_NPY`` (after ``presim refine SCENE``): mean absolute error of raw / refined /
  guided-filtered / median-filtered depth against a clean ground-truth depth (N, H, W) .npy on
  pixels valid in both, the error of filled pixels, coverage and depth-edge misalignment (px).
- ``figure SCENE GT_NPY OUT_PNG``: crop of a colour image with raw (left) and refined (right) depth
  edges in magenta and the true depth edges in green.
- ``fusion SCENE``: per capture frame, AbsRel of the raw / refined / aligned / fused depth (and
  ``fused_est``: ``agree_value="estimate"``) against the sensor depth and, when the scene has
  ``ground_truth/depth_clean.npy`` (the sample scene), against the true depth; coverage; wall and CPU
  time of alignment + fusion per frame (median, after one warm-up). Uses the refined depth that
  ``presim eval-views`` caches for the capture (``SCENE/eval_cache``; computed if missing). AbsRel
  against the sensor measures how far a variant moves away from the measurements (raw is 0 by
  construction); against ground truth it measures accuracy.

    python benchmarks/bench_depth.py refine [--scene SCENE] [--repeats 3]
    python benchmarks/bench_depth.py accuracy SCENE SCENE/ground_truth/depth_clean.npy
    python benchmarks/bench_depth.py figure SCENE SCENE/ground_truth/depth_clean.npy out/edges.png --frame 10
    python benchmarks/bench_depth.py fusion SCENE [--stride S] [--scene-poses refined]
    python benchmarks/bench_depth.py refine --quick        # smoke run (160x120, 1 repeat)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


def _time(fn, repeats: int) -> float:
    """Median wall seconds after one warm-up call (numba compilation / caches)."""
    return common.median_ms(fn, repeats, warmup=1)[0] / 1e3


# ---- accuracy and figure -----------------------------------------------------------------------

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


# ---- refine: speed ---------------------------------------------------------------------------

def cmd_refine(args) -> None:
    from presim.depth.filters import guided_filter_depth, median_filter_depth
    from presim.depth.refine import RefineConfig, RefView, refine_depth, select_reference_views
    from presim.geometry import Intrinsics
    from presim.testing.two_planes import render_two_planes, two_plane_poses

    if args.scene:
        from presim.capture.store import load_scene

        sc = load_scene(args.scene)
        i = min(args.frame, len(sc) - 1)
        f = sc.frame(i)
        color, depth, K, T = f.color, f.depth_m, f.K, f.T_world_cam
        refs = [RefView(*sc.frames.load(j), sc.intrinsics[j], sc.T_world_cam[j])
                for j in select_reference_views(sc.T_world_cam, i, range(len(sc)))]
    else:
        K = Intrinsics.from_fov(*common.parse_size(args.size), 60.0)
        poses = two_plane_poses(11, 0.06)
        views = [render_two_planes(P, K) for P in poses]
        color, depth = views[0]
        depth = depth.copy()
        depth[depth.shape[0] * 5 // 12:depth.shape[0] * 13 // 24, depth.shape[1] * 5 // 32:depth.shape[1] * 9 // 32] = 0
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



# ---- fusion ------------------------------------------------------------------------------------

def _absrel(d: np.ndarray, ref: np.ndarray) -> tuple[float, int]:
    m = (d > 0) & (ref > 0)
    return (float(np.mean(np.abs(d[m] - ref[m]) / ref[m])) if m.any() else float("nan")), int(m.sum())


def cmd_fusion(args) -> None:
    from presim.capture.store import load_scene
    from presim.depth.fuse import FuseConfig, fuse_depth
    from presim.depth.scene_fuse import fuse_one_frame
    from presim.evaluation.eval_views import EvalConfig, _refined_capture_depth, capture_and_targets

    scene = load_scene(args.scene, poses=args.scene_poses)
    capture, _ = capture_and_targets(len(scene), args.stride, 5)
    refined = _refined_capture_depth(scene, capture, EvalConfig(stride=args.stride), None)
    gt_path = args.scene / "ground_truth" / "depth_clean.npy"
    gt_all = np.load(gt_path, mmap_mode="r") if gt_path.is_file() else None
    ks = list(range(len(capture)))
    if args.max_frames:
        ks = ks[:: max(1, len(ks) // args.max_frames)][: args.max_frames]
    names = ("raw", "refined", "aligned", "fused", "fused_est")
    vs_sensor = {n: [] for n in names}
    vs_gt = {n: [] for n in names}
    cover = {n: [] for n in names}
    wall, cpu, moved, src_est = [], [], [], []
    fuse_one_frame(scene.frames.load(capture[0])[1], np.asarray(refined[0]), scene.intrinsics[capture[0]])  # warm-up
    for k in ks:
        i = capture[k]
        raw = scene.frames.load(i)[1]
        est = np.asarray(refined[k])
        t0, c0 = time.perf_counter(), time.process_time()
        al, fu = fuse_one_frame(raw, est, scene.intrinsics[i])
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        moved.append(float(np.any(al.offsets != 0, axis=2).mean()))
        src_est.append(float((fu.source == 2).mean()))
        fe = fuse_depth(al.depth_m, est, FuseConfig(agree_value="estimate"), al.scale).depth_m
        for n, d in zip(names, (raw, est, al.depth_m, fu.depth_m, fe)):
            vs_sensor[n].append(_absrel(d, raw)[0])
            cover[n].append(float((d > 0).mean()))
            if gt_all is not None:
                vs_gt[n].append(_absrel(d, np.asarray(gt_all[i]))[0])
    print(f"{args.scene}: {len(ks)} capture frames (stride {args.stride}), {scene.poses_source} poses")
    hdr = "| depth | AbsRel vs sensor | coverage %" + (" | AbsRel vs ground truth |" if gt_all is not None else " |")
    print(hdr)
    print("|---|---|---|" + ("---|" if gt_all is not None else ""))
    for n in names:
        row = f"| {n} | {np.nanmean(vs_sensor[n]):.4f} | {100 * np.mean(cover[n]):.2f}"
        row += f" | {np.nanmean(vs_gt[n]):.4f} |" if gt_all is not None else " |"
        print(row)
    print(f"pixels moved by the alignment: {100 * np.mean(moved):.2f} %; fused pixels from the estimate: "
          f"{100 * np.mean(src_est):.2f} %")
    print(f"align + fuse per frame: median {1e3 * np.median(wall):.0f} ms wall, {1e3 * np.median(cpu):.0f} ms CPU")



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("refine", help="refine_depth speed vs the filters and the reference")
    p.add_argument("--scene", default=None, help="saved scene (default: analytic two-plane scene)")
    p.add_argument("--frame", type=int, default=10)
    p.add_argument("--size", default="640x480", help="two-plane scene size WxH")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="smoke run: two planes at 160x120, 1 repeat")
    p = sub.add_parser("accuracy", help="errors of refined / filtered depth against a clean depth")
    p.add_argument("scene")
    p.add_argument("gt", metavar="GT_DEPTH_NPY")
    p = sub.add_parser("figure", help="edge-alignment figure (raw vs refined depth edges)")
    p.add_argument("scene")
    p.add_argument("gt", metavar="GT_DEPTH_NPY")
    p.add_argument("out", metavar="OUT_PNG")
    p.add_argument("--frame", type=int, default=10)
    p.add_argument("--box", type=int, nargs=4, default=None, metavar=("X", "Y", "W", "H"),
                   help="crop, pixels (default: the window with the most true depth edges)")
    p = sub.add_parser("fusion", help="depth alignment + fusion: accuracy and time per frame")
    p.add_argument("scene", type=Path)
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--scene-poses", default="auto", choices=("auto", "given", "refined"))
    p.add_argument("--max-frames", type=int, default=None, help="evaluate at most this many capture frames")
    args = ap.parse_args(argv)
    if getattr(args, "quick", False):
        args.size, args.repeats = "160x120", 1
    common.setup()
    if args.cmd == "accuracy":
        accuracy(args.scene, args.gt)
    elif args.cmd == "figure":
        figure(args.scene, args.gt, args.out, args.frame, None if args.box is None else tuple(args.box))
    else:
        {"refine": cmd_refine, "fusion": cmd_fusion}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
