"""``presim objects`` (reconstruct a capture's objects, thesis §5.3.5) and ``presim gen-bop-real``
(the capture's own frames as an annotated BOP split)."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "objects", help="find and reconstruct the objects of a capture into the scene (models, poses)",
        description="Remove the support plane the cameras aim at (table top, bin bottom), cluster what stands "
                    "on it (or take --boxes), and reconstruct each object from the multi-view depth: points seen "
                    "in more than 5 views, merged, outliers removed, colour and normals; a watertight Poisson "
                    "mesh when possible. Replaces the scene's objects (names, ids, an editable 'symmetric' "
                    "flag in scene.json); the scene is unchanged unless everything succeeds.")
    p.add_argument("scene", type=Path, help="saved PreSim scene folder (modified in place)")
    p.add_argument("--boxes", type=Path, default=None,
                   help="JSON with one oriented world box per object (see docs/objects.md) instead of finding them")
    p.add_argument("--all-planes", action="store_true",
                   help="objects on every horizontal plane, not only on the one the cameras aim at")
    p.add_argument("--raw-depth", action="store_true", help="use the raw depth even when refined depth exists")
    p.add_argument("--frame-step", type=int, default=1, help="use every N-th frame (default 1)")
    p.add_argument("--min-views", type=int, default=5,
                   help="keep points seen in MORE than this many frames (default 5, as the thesis)")
    p.add_argument("--dry-run", action="store_true", help="report what would be written; change nothing")
    p.set_defaults(func=_objects)

    q = sub.add_parser(
        "gen-bop-real", help="write the capture's own frames as a BOP split annotated from poses + objects",
        description="Each captured frame with the GT implied by its camera pose and the scene's (reconstructed) "
                    "objects: poses, masks, visible masks, boxes, visib fractions, the captured depth. Shares "
                    "models/ and object ids with `presim gen-bop` into the same --out.")
    q.add_argument("scene", type=Path, help="saved PreSim scene with objects (`presim objects`)")
    q.add_argument("--out", type=Path, required=True, help="BOP dataset root")
    q.add_argument("--split", default="real", help="split folder (default real)")
    q.add_argument("--scene-id", type=int, default=0, help="BOP scene id (default 0)")
    q.add_argument("--frames", default=None, metavar="START:STOP[:STEP][,...]",
                   help="frame positions to write (Python slices joined by commas; default all), e.g. 0:70 "
                        "for a train part, 0:160,180:200 around a held-out block")
    q.add_argument("--objects", default=None, help="objects as gen-bop --objects (default: the scene's own)")
    q.add_argument("--depth-scale", type=float, default=0.1, help="depth PNG unit in mm (default 0.1)")
    q.add_argument("--overwrite", action="store_true", help="replace the split's scene folder")
    q.set_defaults(func=_gen_bop_real)


def _objects(args) -> int:
    from presim.capture.store import load_scene
    from presim.datasets.reconstruct_objects import (
        ObjectReconConfig, find_object_boxes, read_boxes_json, reconstruct_objects, write_objects_into_scene,
    )

    if args.frame_step < 1 or args.min_views < 0:
        raise ValueError("--frame-step must be >= 1 and --min-views >= 0")
    scene = load_scene(args.scene)
    cfg = ObjectReconConfig(refined=not args.raw_depth, frame_step=args.frame_step, min_views=args.min_views,
                            all_planes=args.all_planes)
    if args.boxes is not None:
        boxes, planes = read_boxes_json(args.boxes), []
    else:
        boxes, planes = find_object_boxes(scene, cfg)
    objs, problems = reconstruct_objects(scene, boxes, planes, cfg, strict=args.boxes is not None)
    for msg in problems:
        print(f"skipped: {msg}", file=sys.stderr)
    summary = [{"obj_id": o.obj_id, "name": o.name, **o.stats} for o in objs]
    if not args.dry_run:
        write_objects_into_scene(args.scene, objs)
    print(json.dumps({"scene": str(args.scene), "objects": summary, "skipped": len(problems),
                      "written": not args.dry_run}))
    return 0


def _gen_bop_real(args) -> int:
    from presim.datasets.real_split import RealSplitConfig, parse_frame_range, write_real_split

    cfg = RealSplitConfig(split=args.split, scene_id=args.scene_id, depth_scale=args.depth_scale,
                          frames=None if args.frames is None else parse_frame_range(args.frames))
    rep = write_real_split(args.scene, args.out, cfg, objects_spec=args.objects, overwrite=args.overwrite)
    print(json.dumps(asdict(rep)))
    return 0
