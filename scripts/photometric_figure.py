"""Side-by-side figure for issue 12: real image | today's render | new render, for three targets.

    python scripts/photometric_figure.py SCENE --out docs/img/blend_apc.png [--stride 1 --target-every 5]
        [--targets 5 13 21]

Leave-one-out like ``presim eval-views``: each target (scene position) is rendered from the other
capture frames, on the refined capture depth cached by eval-views (``SCENE/eval_cache``), once with
``RenderConfig()`` ("today", eval-views' ``thesis``) and once with eval-views' ``full`` (photometric
correction matched to the target's exposure + sharpness-aware views + blending of 6 views). Labels
carry each panel's PSNR / SSIM.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    from presim.photometric import calibrate_photometric
    from presim.capture.store import load_scene
    from presim.evaluation.eval_views import (BEST, EvalConfig, _refined_capture_depth, capture_and_targets,
                                              image_metrics)
    from presim.synthesis.renderer import RenderConfig, Renderer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--target-every", type=int, default=5)
    ap.add_argument("--targets", type=int, nargs="*", default=None, help="capture positions (default: 3 spread)")
    ap.add_argument("--scale", type=float, default=0.5, help="panel scale")
    args = ap.parse_args()
    scene = load_scene(args.scene)
    capture, targets = capture_and_targets(len(scene), args.stride, args.target_every)
    cfg = EvalConfig(stride=args.stride, target_every=args.target_every)
    cap = dataclasses.replace(scene.subset(capture), depth_refined=_refined_capture_depth(scene, capture, cfg, None))
    calib = calibrate_photometric(cap, show_progress=False)
    if args.targets:
        targets = args.targets
    else:
        targets = [targets[i] for i in np.linspace(0, len(targets) - 1, 3).round().astype(int)]
    rows = []
    for k in targets:
        f = cap.frame(k)
        loo = dataclasses.replace(cap, photometric=calib).subset([j for j in range(len(cap)) if j != k])
        old = Renderer(dataclasses.replace(loo, photometric=None), RenderConfig()).render(f.T_world_cam, f.K)
        best = {**BEST, "exposure_frame": cap.frame_ids[k]}  # eval-views' "full"
        new = Renderer(loo, RenderConfig(**best)).render(f.T_world_cam, f.K)
        panels = []
        for img, label in ((f.color, f"real {cap.frame_ids[k]}"), (old.color, "today"), (new.color, "new")):
            if label != f"real {cap.frame_ids[k]}":
                m = image_metrics(old if label == "today" else new, f.color, f.depth_m)
                label += f" {m['psnr_db']:.2f} dB SSIM {m['ssim']:.3f}"
            p = cv2.resize(cv2.cvtColor(img, cv2.COLOR_RGB2BGR), None, fx=args.scale, fy=args.scale,
                           interpolation=cv2.INTER_AREA)
            cv2.rectangle(p, (0, 0), (p.shape[1], 22), (0, 0, 0), -1)
            cv2.putText(p, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            panels.append(p)
        rows.append(np.hstack(panels))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.out), np.vstack(rows)):
        raise SystemExit(f"{args.out}: could not write")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
