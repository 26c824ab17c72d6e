"""``presim sample-scene``: build the built-in procedural sample scene."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("sample-scene",
                       help="build the built-in textured sample room (RGB-D frames, exact ground truth)",
                       description="Build the procedural sample room: RGB-D frames with realistically corrupted "
                                   "depth, exact depth/poses/object masks in DST/ground_truth/ (docs/sample-scene.md).")
    p.add_argument("dst", type=Path, help="output scene folder")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed (layout jitter, colors, objects, trajectory, noise)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default 60)")
    p.add_argument("--width", type=int, default=None, help="image width in pixels (default 640)")
    p.add_argument("--height", type=int, default=None, help="image height in pixels (default 480)")
    p.add_argument("--objects", type=int, default=None, help="objects on the table, 3..5 (default 5)")
    p.add_argument("--overwrite", action="store_true", help="replace DST if it exists")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    from presim.limits import check_intrinsics, check_memory, check_positive_int, sample_scene_memory_bytes

    check_intrinsics(args.width, args.height)
    check_positive_int(args.frames, "--frames")
    config0 = SampleSceneConfig()
    w, h = args.width or config0.width, args.height or config0.height
    n = args.frames or config0.num_frames
    check_memory(sample_scene_memory_bytes(w, h, n), f"--width/--height/--frames ({w}x{h}, {n} frames)",
                 "building the sample scene", args.max_memory)
    changes = {k: v for k, v in (("num_frames", args.frames), ("width", args.width), ("height", args.height),
                                 ("num_objects", args.objects)) if v is not None}
    config = dataclasses.replace(SampleSceneConfig(), **changes)
    t0 = time.perf_counter()
    dst = build_sample_scene(args.dst, seed=args.seed, config=config, overwrite=args.overwrite)
    print(f"sample scene (seed {args.seed}, {config.num_frames} frames {config.width}x{config.height}) "
          f"written to {dst} in {time.perf_counter() - t0:.1f} s")
    return 0
