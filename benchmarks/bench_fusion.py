"""Depth alignment + fusion (thesis §5.3.4) on a saved scene: accuracy and time per frame.

    python benchmarks/bench_fusion.py SCENE [--stride S] [--scene-poses refined]

Uses the refined depth that ``presim eval-views`` caches for the same capture (``SCENE/eval_cache``;
computed if missing), so the numbers are those of the depth the ``fused`` method renders with.
Per capture frame: AbsRel of the raw / refined / aligned / fused depth (and ``fused_est``: the
fusion with ``agree_value="estimate"``) against the sensor depth
(pixels where the sensor and the variant both have depth), the coverage of each, and, when the scene
has ``ground_truth/depth_clean.npy`` (the sample scene), AbsRel and coverage against the true depth.
Also the wall and CPU time of alignment + fusion per frame (median over frames, after one warm-up).

What AbsRel against the sensor measures: how far a variant moves away from the measurements where
there are measurements (raw is 0 by construction); it cannot tell a correct edge move or fill from a
wrong one. Against ground truth (sample scene only) it measures accuracy.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.store import load_scene
from presim.depth.fuse import FuseConfig, fuse_depth
from presim.depth.scene_fuse import fuse_one_frame
from presim.evaluation.eval_views import EvalConfig, _refined_capture_depth, capture_and_targets


def _absrel(d: np.ndarray, ref: np.ndarray) -> tuple[float, int]:
    m = (d > 0) & (ref > 0)
    return (float(np.mean(np.abs(d[m] - ref[m]) / ref[m])) if m.any() else float("nan")), int(m.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--scene-poses", default="auto", choices=("auto", "given", "refined"))
    ap.add_argument("--max-frames", type=int, default=None, help="evaluate at most this many capture frames")
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
