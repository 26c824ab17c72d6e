"""``presim render``: synthesize color + depth images of a saved scene at given camera poses."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

__all__ = ["register", "read_tum_poses", "run_render"]


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
    p.add_argument("--width", type=int, help="image width (default: the scene's; intrinsics scaled)")
    p.add_argument("--height", type=int, help="image height (default: the scene's)")
    p.add_argument("--fx", type=float, help="focal length x, pixels (after scaling)")
    p.add_argument("--fy", type=float, help="focal length y, pixels")
    p.add_argument("--cx", type=float, help="principal point x, pixels")
    p.add_argument("--cy", type=float, help="principal point y, pixels")
    p.add_argument("--layers", type=int, default=4, help="number of depth layers L (1 = plain DIBR)")
    p.add_argument("--no-fill", action="store_true", help="leave uncovered pixels empty (black, depth 0)")
    p.add_argument("--raw-depth", action="store_true", help="ignore the scene's refined depth")
    p.add_argument("--backend", default="numba", choices=("numba", "torch", "reference"),
                   help="kernel backend (default numba)")
    p.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="camera poses of the scene: refined by `presim align` when present (auto, default), "
                        "the capture's given ones, or refined (error when absent)")
    p.set_defaults(func=_main)


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: returns ``(stamps_s (B,), T_world_cam (B, 4, 4))``."""
    from presim.geometry import pose_from_tum

    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    stamps, poses = [], []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(f"{path}:{n}: expected 'stamp x y z qx qy qz qw' (8 numbers), got {len(parts)}")
        try:
            vals = np.array([float(x) for x in parts])
        except ValueError:
            raise ValueError(f"{path}:{n}: not a number in {line!r}") from None
        try:
            poses.append(pose_from_tum(vals[1:]))
        except ValueError as e:
            raise ValueError(f"{path}:{n}: {e}") from None
        stamps.append(vals[0])
    if not poses:
        raise ValueError(f"{path}: no poses")
    return np.asarray(stamps), np.stack(poses)


def _intrinsics(scene, args):
    from presim.geometry import Intrinsics

    K = scene.intrinsics[0]
    if args.width or args.height:
        w = args.width or round(K.width * args.height / K.height)
        h = args.height or round(K.height * args.width / K.width)
        K = K.scaled(w, h)
    return Intrinsics(args.fx or K.fx, args.fy or K.fy, K.cx if args.cx is None else args.cx,
                      K.cy if args.cy is None else args.cy, K.width, K.height)


def run_render(scene, T_world_cams: np.ndarray, stamps_s: np.ndarray, K, out: Path, config) -> dict:
    """Render every pose and write ``frame-XXXXXX.{color,depth,valid}.png`` (atomic) into ``out``.

    Depth PNGs are uint16 millimetres (0 = unknown; filled pixels keep their filled depth, the valid
    mask tells them apart). Also writes ``camera-intrinsics.txt``, ``trajectory_tum.txt`` and
    ``render.json``. Returns the summary written to render.json.
    """
    import time

    from presim.geometry import pose_to_tum
    from presim.io_utils import atomic_write_json, atomic_write_text, progress, write_png
    from presim.synthesis.renderer import Renderer

    out.mkdir(parents=True, exist_ok=True)
    r = Renderer(scene, config)
    holes, views, ms = [], [], []
    for i in progress(range(len(T_world_cams)), desc="render", unit="frame"):
        t0 = time.perf_counter()
        rgbd = r.render(T_world_cams[i], K)
        ms.append((time.perf_counter() - t0) * 1e3)
        name = f"frame-{i:06d}"
        write_png(out / f"{name}.color.png", rgbd.color)
        depth_mm = np.clip(np.round(rgbd.depth_m.astype(np.float64) * 1000.0), 0, 65535).astype(np.uint16)
        write_png(out / f"{name}.depth.png", depth_mm)
        write_png(out / f"{name}.valid.png", rgbd.valid)
        holes.append(rgbd.hole_frac_before_fill)
        views.append(len(r.last.views))
    atomic_write_text(out / "camera-intrinsics.txt",
                      "\n".join(" ".join(f"{x:.6f}" for x in row) for row in K.K) + "\n")
    atomic_write_text(out / "trajectory_tum.txt", "".join(
        f"{s:.6f} " + " ".join(f"{x:.9f}" for x in pose_to_tum(T)) + "\n" for s, T in zip(stamps_s, T_world_cams)))
    summary = {
        "scene": str(scene.path) if scene.path else None, "num_frames": len(T_world_cams),
        "intrinsics": K.to_dict(), "config": dataclasses.asdict(config),
        "hole_frac_before_fill": holes, "views_used": views,
        "ms_per_frame_median": float(np.median(ms)),
    }
    atomic_write_json(out / "render.json", summary)
    return summary


def _main(args: argparse.Namespace) -> int:
    from presim.capture.store import is_scene_dir, load_scene
    from presim.geometry import pose_from_tum
    from presim.synthesis.renderer import RenderConfig

    if not args.scene.exists():
        raise FileNotFoundError(f"{args.scene}: scene folder not found")
    if not is_scene_dir(args.scene):
        raise FileNotFoundError(f"{args.scene}: not a saved scene (no scene.json); import it with `presim import`")
    scene = load_scene(args.scene, poses=args.scene_poses)
    if args.pose is not None:
        vals = args.pose.replace(",", " ").split()
        if len(vals) != 7:
            raise ValueError(f"--pose needs 7 numbers 'x y z qx qy qz qw', got {len(vals)}")
        T = pose_from_tum(np.array([float(v) for v in vals]))[None]
        stamps = np.zeros(1)
    elif args.poses is not None:
        stamps, T = read_tum_poses(args.poses)
    else:
        if not 0 <= args.frame < len(scene):
            raise ValueError(f"--frame {args.frame}: the scene has frames 0..{len(scene) - 1}")
        T = scene.T_world_cam[args.frame][None]
        stamps = scene.stamps_s[args.frame:args.frame + 1]
    if args.layers < 1:
        raise ValueError(f"--layers must be >= 1, got {args.layers}")
    config = RenderConfig(num_layers=args.layers, fill_holes=not args.no_fill,
                          use_refined_depth=not args.raw_depth, backend=args.backend)
    K = _intrinsics(scene, args)
    s = run_render(scene, T, stamps, K, args.out, config)
    print(f"wrote {s['num_frames']} frame(s) to {args.out} ({K.width}x{K.height}, "
          f"median {s['ms_per_frame_median']:.1f} ms/frame, mean hole fraction before fill "
          f"{np.mean(s['hole_frac_before_fill']):.4f})")
    return 0
