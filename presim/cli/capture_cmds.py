"""``presim import`` and ``presim info``."""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path


def register(sub) -> None:
    from presim.capture.importers.registry import ALIASES, FORMATS

    p = sub.add_parser(
        "import", help="import an RGB-D capture folder (format auto-detected) into a PreSim scene",
        description="Read a capture (KinectFusion/7-Scenes, APC shelf, TUM RGB-D, COLMAP + depth, nerfstudio, "
                    "BOP, YCB-Video), fuse its point cloud, align the floor (gravity -z, floor z = 0) and save it. "
                    "A capture without poses (KinectFusion layout without frame-*.pose.txt, TUM folder without "
                    "groundtruth.txt) gets them by structure from motion: pycolmap (pip install 'presim[sfm]'; "
                    "there is no other pose estimator) extracts SIFT, matches each frame to its next 10 (plus "
                    "quadratic jumps) and to its most similar frames by a bag of words built on the capture "
                    "(loop closure), maps incrementally with the known intrinsics held fixed; the metric scale "
                    "comes from the sensor depth; then the local-to-global alignment of `presim align` runs. "
                    "Frames the mapper cannot register are named and left out; if fewer than --min-registered "
                    "register, nothing is written. See docs/alignment.md.")
    p.add_argument("src", type=Path, help="capture folder (or transforms.json)")
    p.add_argument("dst", type=Path, help="output scene folder")
    p.add_argument("--format", dest="fmt", choices=sorted(FORMATS) + sorted(ALIASES), default=None, metavar="F",
                   help=f"force a format: {', '.join(sorted(FORMATS))} (aliases: {', '.join(sorted(ALIASES))})")
    p.add_argument("--every", type=int, default=1, metavar="N", help="keep every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, default=None, metavar="M", help="keep at most M frames")
    p.add_argument("--gravity", type=float, nargs=3, default=None, metavar=("GX", "GY", "GZ"),
                   help="gravity direction in the capture's world frame (default: from the cameras' up axes)")
    p.add_argument("--no-floor", action="store_true", help="keep the capture's world frame (no floor alignment)")
    p.add_argument("--overwrite", action="store_true", help="replace DST if it exists")
    p.add_argument("--depth-scale", type=float, default=None, metavar="MM",
                   help="millimetres per step of the depth images (depth_mm = value * MM, the BOP convention), "
                        "replacing the format's own unit; needed to import 8-bit depth images")
    p.add_argument("--min-registered", type=float, default=0.8, metavar="FRAC",
                   help="captures without poses: fail (writing nothing) when SfM registers fewer than this "
                        "fraction of the frames (default 0.8)")
    p.add_argument("--sfm-seed", type=int, default=0,
                   help="captures without poses: SfM seed (same seed = same poses; default 0)")
    p.add_argument("--sfm-threads", type=int, default=1, metavar="N",
                   help="captures without poses: threads for SIFT extraction and matching (default 1, "
                        "reproducible; -1 = all cores, faster, reproducibility not tested)")
    p.set_defaults(func=_cmd_import)

    q = sub.add_parser("info", help="summarise a scene: frames, resolution, depth coverage, extent, trajectory",
                       description="Print what a saved scene holds.")
    q.add_argument("scene", type=Path, help="scene folder (written by `presim import` or `presim sample-scene`)")
    q.add_argument("--json", action="store_true", help="print JSON instead of text")
    q.add_argument("--sample-frames", type=int, default=50, help="frames sampled for depth coverage (default 50)")
    q.set_defaults(func=_cmd_info)


def _cmd_import(args: argparse.Namespace) -> int:
    from presim.align.sfm import SfmConfig, estimate_poses
    from presim.capture.importers import import_capture
    from presim.capture.info import format_info, scene_info
    from presim.capture.store import load_scene, save_scene

    if args.dst.exists() and not args.overwrite:
        raise FileExistsError(f"{args.dst}: already exists (pass --overwrite to replace it)")
    if not 0 < args.min_registered <= 1:
        raise ValueError(f"--min-registered must be in (0, 1], got {args.min_registered}")
    scene = import_capture(args.src, fmt=args.fmt, every=args.every, max_frames=args.max_frames,
                           gravity=args.gravity, align_floor=not args.no_floor,
                           estimate_poses=functools.partial(estimate_poses, config=SfmConfig(
                               min_registered_frac=args.min_registered, seed=args.sfm_seed,
                               num_threads=args.sfm_threads)),
                           depth_scale_mm=args.depth_scale)
    save_scene(scene, args.dst, overwrite=args.overwrite)
    saved = load_scene(args.dst)
    print(format_info(scene_info(saved, max_sample_frames=10)))
    print(f"wrote {args.dst}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from presim.capture.info import format_info, scene_info
    from presim.capture.store import load_scene

    info = scene_info(load_scene(args.scene), max_sample_frames=max(1, args.sample_frames))
    if args.json:
        json.dump(info, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(format_info(info))
    return 0
