"""``presim render``: synthesize color + depth images of a saved scene at given camera poses."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

__all__ = ["register"]


def register(sub) -> None:
    p = sub.add_parser("render", help="render color + 16-bit depth PNGs of a scene at camera poses",
                       description="Synthesize RGB-D images of a saved scene (thesis Ch. 3) at one pose, "
                                   "a TUM trajectory, or the pose of one of its frames.")
    p.add_argument("scene", type=Path, help="saved scene folder (presim import / presim sample-scene)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--pose", help='camera pose T_world_cam as "x y z qx qy qz qw" (OpenCV camera)')
    g.add_argument("--poses", type=Path, help="TUM trajectory file: lines 'stamp x y z qx qy qz qw'")
    g.add_argument("--frame", type=int, help="render at the pose of the scene frame at this position")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument("--width", type=int, help="image width (default: the scene's; with only --height, the "
                                             "width that keeps the scene's aspect ratio); intrinsics scaled")
    p.add_argument("--height", type=int, help="image height (default: the scene's; with only --width, the "
                                              "height that keeps the scene's aspect ratio); intrinsics scaled")
    p.add_argument("--fx", type=float, help="focal length x, pixels (default: the scene's, after scaling)")
    p.add_argument("--fy", type=float, help="focal length y, pixels (default: the scene's, after scaling)")
    p.add_argument("--cx", type=float, help="principal point x, pixels (default: the scene's, after scaling)")
    p.add_argument("--cy", type=float, help="principal point y, pixels (default: the scene's, after scaling)")
    p.add_argument("--layers", type=int, default=4, help="number of depth layers L (1 = plain DIBR)")
    p.add_argument("--no-fill", action="store_true", help="leave uncovered pixels empty (black, depth 0)")
    p.add_argument("--raw-depth", action="store_true", help="ignore the scene's refined depth")
    p.add_argument("--fused-depth", action="store_true",
                   help="use the scene's fused depth (presim fuse) instead of the refined depth")
    p.add_argument("--backend", default="numba", choices=("numba", "torch", "reference"),
                   help="kernel backend (default numba; torch runs on CUDA when present, else CPU)")
    p.add_argument("--batch-size", type=int, default=16,
                   help="poses per Renderer.render_batch call; pose i continues the camera stream of pose "
                        "i - batch size (default 16)")
    p.add_argument("--min-view-gain", type=float, default=None, metavar="F",
                   help="adaptive loop: warp a further view only when it is predicted to fill at least this "
                        "fraction of the image (default 0.005; 0 = the thesis's loop, every view that can fill "
                        "a big hole, up to 6)")
    p.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    p.set_defaults(func=_main)


def _main(args: argparse.Namespace) -> int:
    from presim.capture.open import open_scene
    from presim.formats.tum import read_tum
    from presim.geometry import pose_from_tum
    from presim.limits import check_intrinsics, check_positive_int
    from presim.cli.render_job import far_poses, output_intrinsics, render_to_folder
    from presim.synthesis.renderer import PerfConfig, RenderConfig

    check_intrinsics(args.width, args.height, args.fx, args.fy, args.cx, args.cy)
    check_positive_int(args.layers, "--layers", allow_none=False)
    check_positive_int(args.batch_size, "--batch-size", allow_none=False)
    scene = open_scene(args.scene, poses=args.scene_poses)
    if args.pose is not None:
        vals = args.pose.replace(",", " ").split()
        if len(vals) != 7:
            raise ValueError(f"--pose needs 7 numbers 'x y z qx qy qz qw', got {len(vals)}")
        try:
            T = pose_from_tum(np.array([float(v) for v in vals]))[None]
        except ValueError as e:
            raise ValueError(f"--pose {args.pose!r}: {e}") from None
        stamps = np.zeros(1)
    elif args.poses is not None:
        stamps, T = read_tum(args.poses)
    else:
        if not 0 <= args.frame < len(scene):
            raise ValueError(f"--frame {args.frame}: the scene has frames 0..{len(scene) - 1}")
        T = scene.T_world_cam[args.frame][None]
        stamps = scene.stamps_s[args.frame:args.frame + 1]
    if args.layers < 1:
        raise ValueError(f"--layers must be >= 1, got {args.layers}")
    if args.fused_depth and args.raw_depth:
        raise ValueError("--fused-depth and --raw-depth exclude each other")
    if args.fused_depth and scene.depth_fused is None:
        raise ValueError(f"--fused-depth: {args.scene} has no depth_fused.npy (run `presim fuse {args.scene}`)")
    gain = {}
    if args.min_view_gain is not None:
        if not 0.0 <= args.min_view_gain < 1.0:  # also rejects nan
            raise ValueError(f"--min-view-gain must be in [0, 1), got {args.min_view_gain}")
        gain = {"min_view_gain": args.min_view_gain}
    config = RenderConfig(num_layers=args.layers, fill_holes=not args.no_fill,
                          use_refined_depth=not args.raw_depth, use_fused_depth=args.fused_depth, **gain)
    K = output_intrinsics(scene.intrinsics[0], args.width, args.height, args.fx, args.fy, args.cx, args.cy)
    from presim.limits import check_render_memory

    check_render_memory(K.width, K.height, args.layers, args.max_memory)
    s = render_to_folder(scene, T, stamps, K, args.out, config, batch_size=args.batch_size,
                         perf=PerfConfig(backend=args.backend))
    print(f"wrote {s['num_frames']} frame(s) to {args.out} ({K.width}x{K.height}, "
          f"median {s['ms_per_frame_median']:.1f} ms/frame, mean hole fraction before fill "
          f"{np.mean(s['hole_frac_before_fill']):.4f})")
    if s["depth_clipped_px"]:
        print(f"  {s['depth_clipped_px']} depth pixels beyond 65.535 m written as 0 (invalid)")
    for w in far_poses(scene, T, s["hole_frac_before_fill"]):
        print(f"warning: {w}", file=sys.stderr)
    return 0
