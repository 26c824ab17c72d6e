"""``presim gen-bop``: write a 6D-pose dataset in BOP format from a scene (thesis §5.3.6-5.3.7)."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "gen-bop", help="generate a 6D-pose dataset in BOP format (RGB-D, poses, masks, boxes) from a scene",
        description="Sample camera poses around each object (seed views that see it, <=30 deg / <=0.2 m "
                    "perturbations), synthesize RGB-D, annotate every object, write a BOP scene. "
                    "Resumable: rerun the same command after an interruption.")
    p.add_argument("scene", type=Path, help="saved PreSim scene folder")
    p.add_argument("--objects", default=None,
                   help="objects: JSON file, bop:SCENE_DIR or ycbv:DIR (default: the scene's own objects)")
    p.add_argument("--frames", type=int, default=100, help="number of images (default 100)")
    p.add_argument("--out", type=Path, required=True, help="BOP dataset root to write")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed = same dataset)")
    p.add_argument("--width", type=int, default=1280, help="image width (default 1280, as the thesis)")
    p.add_argument("--height", type=int, default=720, help="image height (default 720)")
    p.add_argument("--hfov-deg", type=float, default=None, help="horizontal field of view (default: the scene's)")
    p.add_argument("--split", default="train", help="BOP split folder (default train)")
    p.add_argument("--scene-id", type=int, default=0, help="BOP scene id (default 0)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (or Ray actors with --ray)")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run on a Ray cluster at ADDRESS ('local': a private instance on 127.0.0.1)")
    p.add_argument("--coco", action="store_true", help="also write scene_gt_coco.json (COCO instances)")
    p.add_argument("--min-visib", type=float, default=0.1,
                   help="drop frames whose target is less visible than this fraction (default 0.1)")
    p.add_argument("--max-rotation-deg", type=float, default=30.0, help="largest rotation from a seed view")
    p.add_argument("--max-translation-m", type=float, default=0.2, help="largest translation from a seed view")
    p.add_argument("--max-roll-deg", type=float, default=5.0, help="largest roll about the optical axis")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png", help="color image format")
    p.add_argument("--depth-scale", type=float, default=0.1,
                   help="depth PNG unit in mm (depth_mm = value * scale; default 0.1)")
    p.add_argument("--visib-tolerance-m", type=float, default=0.015,
                   help="visibility test tolerance (BOP delta, default 0.015 m)")
    p.add_argument("--overwrite", action="store_true", help="replace a scene written by a different job")
    p.add_argument("--max-new-frames", type=int, default=None,
                   help="make at most this many new frames then stop (time-sliced jobs; rerun to continue)")
    p.add_argument("--validate", action="store_true", help="validate the written dataset at the end")
    p.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    p.add_argument("--source-frames", default=None, metavar="START:STOP[:STEP][,...]",
                   help="capture frames the synthesis may use as seed and source views (Python slices of frame "
                        "positions joined by commas, e.g. 0:40 or 0:160,180:200; default all): keeps held-out capture frames out of training data")
    p.set_defaults(func=_gen_bop)


def _gen_bop(args) -> int:
    from presim.capture.store import load_scene
    from presim.datasets.annotate import AnnotateConfig
    from presim.datasets.camera_sampling import CameraSamplingConfig
    from presim.datasets.generate import GenConfig, generate_bop, report_path
    from presim.datasets.object_sources import resolve_objects
    from presim.datasets.real_split import parse_frame_range

    from presim.datasets.generate import MAX_FRAMES, check_depth_scale
    from presim.limits import (
        GEN_BOP_RECORD_BYTES, InputError, check_disk, check_intrinsics, check_memory, check_positive,
        check_positive_int, check_render_memory, gen_bop_output_bytes,
    )

    check_intrinsics(args.width, args.height)
    check_positive_int(args.frames, "--frames", allow_none=False)
    if args.frames > MAX_FRAMES:
        raise InputError("--frames", f"at most {MAX_FRAMES} images per BOP scene (6-digit image ids), got "
                                     f"{args.frames}; split the job over several --scene-id")
    check_positive_int(args.workers, "--workers", allow_none=False)
    check_positive(args.hfov_deg, "--hfov-deg")
    check_depth_scale(args.depth_scale, "--depth-scale")
    check_render_memory(args.width, args.height, max_memory=args.max_memory, copies=args.workers,
                        per_frame_extra_px_bytes=32.0, what=f"generating frames ({args.workers} worker(s))")
    check_memory(float(args.frames) * GEN_BOP_RECORD_BYTES, "--frames", f"keeping {args.frames} frame records",
                 args.max_memory)
    check_disk(gen_bop_output_bytes(args.width, args.height, args.frames), args.out, "--frames/--width/--height",
               f"writing {args.frames} images of {args.width}x{args.height}")
    scene = load_scene(args.scene, poses=args.scene_poses)
    objects = resolve_objects(scene, args.objects)
    config = GenConfig(
        frames=args.frames, seed=args.seed, width=args.width, height=args.height, hfov_deg=args.hfov_deg,
        split=args.split, scene_id=args.scene_id, image_format=args.image_format, depth_scale=args.depth_scale,
        min_visib_fract=args.min_visib, coco=args.coco,
        sampling=CameraSamplingConfig(max_rotation_deg=args.max_rotation_deg,
                                      max_translation_m=args.max_translation_m, max_roll_deg=args.max_roll_deg),
        annotate=AnnotateConfig(visib_tolerance_m=args.visib_tolerance_m),
        source_frames=None if args.source_frames is None else parse_frame_range(args.source_frames,
                                                                                "--source-frames"),
    )
    rep = generate_bop(args.scene, args.out, objects, config, workers=args.workers, ray_address=args.ray,
                       overwrite=args.overwrite, stop_after=args.max_new_frames,
                       scene_poses=args.scene_poses, wait=not args.no_wait)
    d = asdict(rep)
    print(json.dumps({k: d[k] for k in ("scene_dir", "frames_written", "frames_requested", "dropped_not_visible",
                                        "slots_failed", "instances", "finished", "complete", "frames_per_s")}))
    if not rep.finished:
        print(f"stopped before the end: rerun the same command to continue {rep.scene_dir}", file=sys.stderr)
        return 0
    print(f"report: {report_path(args.out, config.split, config.scene_id)}", file=sys.stderr)
    if 0 < rep.frames_written < rep.frames_requested:
        print(f"warning: incomplete: {rep.frames_requested - rep.frames_written} of {rep.frames_requested} image "
              f"slot(s) made no frame (slots {rep.slots_failed[:10]}{' ...' if len(rep.slots_failed) > 10 else ''}; "
              "every attempt rejected, see the report's 'rejected')", file=sys.stderr)
    no_seed = rep.rejected.get("no_seed_view", 0)
    if no_seed:
        print(f"warning: {no_seed} image slot(s) targeted an object that no captured view sees (object outside "
              "the captured area, or its pose/model in the wrong unit?)", file=sys.stderr)
    if rep.frames_written == 0 and rep.frames_requested > 0:
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(rep.rejected.items())) or "none recorded"
        print(f"presim gen-bop: error: no image could be made (rejections: {reasons}); "
              "check --objects and the scene", file=sys.stderr)
        return 1
    if args.validate:
        from presim.datasets.validate import validate_bop

        problems = validate_bop(args.out, splits=(config.split,))
        for p in problems:
            print(f"invalid: {p}", file=sys.stderr)
        return 1 if problems else 0
    return 0
