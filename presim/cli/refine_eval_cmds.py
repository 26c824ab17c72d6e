"""``presim refine`` (offline depth refinement), ``presim fuse`` (depth alignment and fusion) and
``presim eval-views`` (leave-one-out evaluation)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("refine", help="refine the depth of every frame of a scene (thesis §3.4.1)",
                       description="Writes SCENE/depth_refined.npy (raw depth.npy untouched); frames run in "
                                   "parallel processes; an interrupted run resumes.")
    p.add_argument("scene", type=Path, help="saved scene folder")
    p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
    p.add_argument("--overwrite", action="store_true", help="recompute an existing depth_refined.npy")
    p.add_argument("--num-refs", type=int, default=10, help="reference views per frame (thesis: 10)")
    p.add_argument("--sharp-refs", action="store_true",
                   help="down-weight blurred reference frames in the photo-consistency cost (sharpness score)")
    p.add_argument("--no-complete", action="store_true",
                   help="do not complete the refined depth afterwards (presim complete)")
    p.add_argument("--no-fit-filter", action="store_true",
                   help="do not fit the renderer's reconstruction filter afterwards (presim fit-filter)")
    p.set_defaults(func=_refine)

    ff = sub.add_parser("fit-filter", help="fit the renderer's reconstruction filter on the capture",
                        description="Renders capture frames spread over the capture from the other frames, "
                                    "then picks the Gaussian sigma of the output filter that makes them closest "
                                    "to the real frames (mean PSNR on covered pixels), and writes "
                                    "SCENE/render_filter.json, which the renderer's default then uses. "
                                    "`presim refine` runs it at its end; --sigma sets it by hand.")
    ff.add_argument("scene", type=Path, help="saved scene folder")
    ff.add_argument("--frames", type=int, default=8, help="capture frames rendered (default 8)")
    ff.add_argument("--sigma", type=float, default=None, help="write this sigma (pixels) instead of fitting one")
    ff.set_defaults(func=_fit_filter)

    c = sub.add_parser("complete", help="complete each frame's depth where the sensor has none (borders, dark or "
                                        "shiny surfaces)",
                       description="Continues the neighbouring surfaces into the empty pixels (colour-aware plane "
                                   "fits), keeps a completed pixel only where the nearest views agree "
                                   "(free-space and photometric check), and writes SCENE/depth_completed.npy "
                                   "atomically. The renderer uses it only for pixels no measured depth covers. "
                                   "Works on the refined depth when the scene has it, else the raw depth; "
                                   "`presim refine` runs it at its end.")
    c.add_argument("scene", type=Path, help="saved scene folder")
    c.add_argument("--overwrite", action="store_true", help="recompute an existing depth_completed.npy")
    c.set_defaults(func=_complete)

    f = sub.add_parser("fuse", help="align the sensor depth to the refined depth and fuse them (thesis §5.3.4)",
                       description="Needs SCENE/depth_refined.npy (presim refine). Per frame, aligns the sensor "
                                   "depth to the refined depth (offset map, Alg. 2) and fuses both (sensor values "
                                   "where they agree, the refined depth at edges and where the sensor has none); "
                                   "writes SCENE/depth_fused.npy atomically (depth.npy and depth_refined.npy "
                                   "untouched). `presim render --fused-depth` and `eval-views --methods fused` "
                                   "use it.")
    f.add_argument("scene", type=Path, help="saved scene folder with refined depth")
    f.add_argument("--overwrite", action="store_true", help="recompute an existing depth_fused.npy")
    f.add_argument("--max-offset", type=int, default=8, help="largest alignment offset per axis, pixels (default 8)")
    f.add_argument("--max-range", type=float, default=8.0,
                   help="farthest depth the sensor measures, metres (MaxD of eq. 5.7; default 8.0)")
    f.add_argument("--agree-value", choices=("sensor", "estimate"), default="sensor",
                   help="where sensor and refined depth agree (within 3 %%), keep the sensor's value (default) or "
                        "the refined one")
    f.set_defaults(func=_fuse)

    e = sub.add_parser("eval-views", help="leave-one-out view synthesis evaluation with ablations and a TSDF baseline",
                       description="Capture = every S-th frame; targets = capture positions that are positive "
                                   "multiples of E, each rendered from the other capture frames.")
    e.add_argument("scene", type=Path, help="saved scene folder")
    e.add_argument("--stride", type=int, default=1, help="capture = every S-th frame (default 1)")
    e.add_argument("--target-every", type=int, default=5, help="targets = capture positions k*E, k >= 1 (default 5)")
    e.add_argument("--methods", nargs="+", default=None,
                   help="methods (default all): full thesis default DIBR DIBR_DR LDIBR LDIBR_DR sel_distance sel_angle fixed_1 "
                        "fixed_2 fixed_3 median_plain depth_guided depth_median layers_1..layers_8 tsdf_mesh; "
                        "beyond the thesis: photo photo_mean blend blend_2 blend_6 photo_blend sharp sharp_blend "
                        "photo_sharp_blend photo_sharp_blend_6 fused full_fused fused_est. Every method but `default` "
                        "(RenderConfig() as `presim render` uses it) runs the thesis's adaptive loop (min_view_gain 0)")
    e.add_argument("--json", type=Path, default=None, help="write the metrics as JSON here")
    e.add_argument("--save-images", type=Path, default=None, metavar="DIR",
                   help="write a strip per target and method (real | rendered | |error| 0-64 levels | holes "
                        "before fill) and DIR/report.md (table, the five worst targets first)")
    e.add_argument("--strip-width", type=int, default=None, metavar="PX",
                   help="width of each strip panel in pixels (default: the target's width)")
    e.add_argument("--max-targets", type=int, default=None, help="evaluate at most M targets (evenly spread)")
    e.add_argument("--cache-dir", type=Path, default=None,
                   help="where the capture's refined depth is cached (default SCENE/eval_cache)")
    e.add_argument("--workers", type=int, default=1, help="processes for the refinement of the capture")
    e.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    e.add_argument("--sharp-refs", action="store_true",
                   help="refine the capture's depth with blurred references down-weighted (cached separately)")
    e.add_argument("--no-warmup", action="store_true",
                   help="render each target once (ms/frame then includes preparing the views; quality is the same)")
    e.set_defaults(func=_eval)


def _refine(args) -> int:
    from presim.capture.store import load_scene
    from presim.depth.refine import RefineConfig
    from presim.depth.scene_refine import refine_scene

    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    scene = load_scene(args.scene)
    out = refine_scene(scene, workers=args.workers, overwrite=args.overwrite,
                       config=RefineConfig(num_refs=args.num_refs, sharp_refs=args.sharp_refs))
    print(f"wrote {out}")
    if not args.no_complete:  # the completion of the new refined depth replaces any older one
        from presim.depth.complete import complete_scene

        print(f"wrote {complete_scene(load_scene(args.scene), overwrite=True)}")
    if not args.no_fit_filter:  # fitted on the depth just written
        if len(scene) < 2:
            print(f"fit-filter: skipped, {args.scene} has one frame (the fit renders frames from the others)")
        else:
            _fit_filter(argparse.Namespace(scene=args.scene, frames=8, sigma=None))
    return 0


def _fit_filter(args) -> int:
    from presim.capture.store import load_scene, save_render_filter
    from presim.evaluation.smooth_fit import SmoothFitConfig, fit_smoothing

    scene = load_scene(args.scene)
    if args.sigma is not None:
        print(f"wrote {save_render_filter(args.scene, args.sigma, {'set_by_hand': True})}: sigma {args.sigma:g} px")
        return 0
    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    fit = fit_smoothing(scene, SmoothFitConfig(max_frames=args.frames))
    if not fit.frames:
        print(f"fit-filter: no frame could be scored (views covered < 20 % of each); {args.scene} keeps no filter")
        return 0
    row = lambda s: next(p for x, p in zip(fit.sigmas_px, fit.psnr_db) if x == s)  # noqa: E731
    print(f"fit-filter: {len(fit.frames)} frames; covered-pixel PSNR {row(0.0):.2f} dB unfiltered, "
          f"{row(fit.sigma_px):.2f} dB at sigma {fit.sigma_px:g} px")
    print(f"wrote {save_render_filter(args.scene, fit.sigma_px, fit.to_json())}")
    return 0


def _complete(args) -> int:
    import time

    import numpy as np

    from presim.capture.store import load_scene
    from presim.depth.complete import complete_scene

    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    out = complete_scene(scene, overwrite=args.overwrite)
    done = np.load(out, mmap_mode="r")
    frac = float(np.mean([(done[i] > 0).mean() for i in range(len(scene))]))
    print(f"wrote {out}: {len(scene)} frames, {100 * frac:.2f} % of pixels completed, "
          f"{(time.perf_counter() - t0) / len(scene) * 1e3:.0f} ms per frame")
    return 0


def _fuse(args) -> int:
    import time

    from presim.capture.open import open_scene
    from presim.depth.align import AlignConfig
    from presim.depth.fuse import FuseConfig
    from presim.depth.scene_fuse import fuse_scene

    if args.max_offset < 0:
        raise ValueError(f"--max-offset must be >= 0, got {args.max_offset}")
    if not args.max_range > 0.2:
        raise ValueError(f"--max-range must be > 0.2 m, got {args.max_range}")
    scene = open_scene(args.scene)
    t0, c0 = time.perf_counter(), time.process_time()
    out = fuse_scene(scene, overwrite=args.overwrite, align=AlignConfig(max_offset_px=args.max_offset),
                     fuse=FuseConfig(max_range_m=args.max_range, agree_value=args.agree_value))
    n = len(scene)
    print(f"wrote {out}: {n} frames, {(time.perf_counter() - t0) / n * 1e3:.0f} ms wall / "
          f"{(time.process_time() - c0) / n * 1e3:.0f} ms CPU per frame")
    return 0


def _eval(args) -> int:
    from presim.capture.store import load_scene
    from presim.io_utils import atomic_write_json
    from presim.depth.refine import RefineConfig
    from presim.evaluation.eval_views import DEFAULT_METHODS, EvalConfig, eval_views, format_table

    scene = load_scene(args.scene, poses=args.scene_poses)
    print(f"{args.scene}: {scene.poses_source} poses", file=sys.stderr)
    cfg = EvalConfig(stride=args.stride, target_every=args.target_every,
                     methods=tuple(args.methods) if args.methods else DEFAULT_METHODS,
                     max_targets=args.max_targets, refine_workers=args.workers, warmup=not args.no_warmup,
                     refine=RefineConfig(sharp_refs=args.sharp_refs))
    if args.strip_width is not None and args.strip_width < 16:
        raise ValueError(f"--strip-width must be >= 16 pixels, got {args.strip_width}")
    res = eval_views(scene, cfg, cache_dir=args.cache_dir, log=lambda s: print(s, file=sys.stderr),
                     images_dir=args.save_images, strip_width=args.strip_width)
    print(f"{args.scene}: {len(res.target_ids)} targets, stride {args.stride}, target every {args.target_every}")
    print(format_table(res))
    if args.json is not None:
        atomic_write_json(args.json, json.loads(json.dumps(res.to_json(), allow_nan=True)))
        print(f"wrote {args.json}")
    if args.save_images is not None:
        print(f"wrote {args.save_images / 'report.md'} and {len(res.target_ids) * len(res.methods)} strips")
    return 0
