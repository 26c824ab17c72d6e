"""``presim demo``: the README's main job on the built-in sample scene.

Runs the same sub-commands a user would, in order, each resumable: build the sample scene, (with
--refine) refine its depth, drive the default robot along a built-in route while recording (MCAP +
capture folder) and logging to the viewer (.rrd), write a small BOP dataset, and score the pose
evaluator on it twice: the dataset's ground truth as estimates (must give 100%) and a seeded noisy
copy of it (5 mm, 2 deg), a baseline whose scores are known to be below 100%.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="the main job on the built-in sample scene: build, drive+record+view, BOP dataset, pose eval",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", type=Path, nargs="?", default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample scene, route and dataset")
    p.add_argument("--steps", type=int, default=150, help="simulator steps of the drive")
    p.add_argument("--bop-frames", type=int, default=12, help="frames of the BOP dataset")
    p.add_argument("--bop-size", type=int, nargs=2, default=(640, 360), metavar=("W", "H"),
                   help="BOP image size (default 640 360; the thesis used 1280 720)")
    p.add_argument("--refine", action="store_true",
                   help="also run offline depth refinement (about 1.4 s per frame per worker, 2 workers)")
    p.add_argument("--viewer", choices=["rrd", "native", "web"], default="rrd",
                   help="rrd: only write the .rrd file (default); native/web: also show it live")
    p.set_defaults(func=run)


def _step(title: str, argv: list[str]) -> None:
    from presim.cli import main

    print(f"\n== {title}\n$ presim {' '.join(argv)}", flush=True)
    t0 = time.perf_counter()
    rc = main(argv)
    if rc != 0:
        raise SystemExit(f"presim demo: step '{title}' failed (exit code {rc})")
    print(f"   ({time.perf_counter() - t0:.1f} s)", flush=True)


def _sample_seed(scene: Path) -> int | None:
    """The seed of the built-in sample scene at ``scene`` (None: not a sample scene)."""
    import json

    try:
        return int(json.loads((scene / "ground_truth" / "sample.json").read_text())["seed"])
    except (ValueError, OSError, KeyError, TypeError):
        return None


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    scene = out / "scene"
    seed = str(args.seed)
    if not (scene / "scene.json").is_file():
        _step("build the sample scene", ["sample-scene", str(scene), "--seed", seed])
    elif _sample_seed(scene) not in (None, args.seed):  # a sample scene of another seed: rebuild
        _step("rebuild the sample scene for this seed", ["sample-scene", str(scene), "--seed", seed, "--overwrite"])
    else:
        print(f"using the existing scene {scene}", flush=True)
    _step("scene summary", ["info", str(scene)])
    if args.refine:
        _step("refine depth (offline, resumable)", ["refine", str(scene), "--workers", "2"])
    drive = out / "drive"
    _step("drive the robot, record and log to the viewer",
          ["drive", str(scene), "--steps", str(args.steps), "--seed", seed, "--record", str(drive),
           "--overwrite", "--viewer", args.viewer, "--rrd", str(out / "drive.rrd")])
    bop = out / "bop"
    _step("write a BOP dataset", ["gen-bop", str(scene), "--frames", str(args.bop_frames), "--out", str(bop),
                                  "--seed", seed, "--width", str(args.bop_size[0]),
                                  "--height", str(args.bop_size[1]), "--validate"])
    from presim.pose.results import estimates_from_gt, write_bop_results

    for name, nt, nr in (("gt", 0.0, 0.0), ("gt_noisy", 0.005, 2.0)):
        csv_path = out / f"{name}.csv"
        write_bop_results(csv_path, estimates_from_gt(bop, split="train", noise_t_m=nt, noise_rot_deg=nr,
                                                      seed=args.seed))
        _step(f"score {name}.csv (ground truth{' + 5 mm / 2 deg noise' if nt else ''}) with the pose evaluator",
              ["pose-eval", "--dataset", str(bop), "--split", "train", "--results", str(csv_path),
               "--out", str(out / f"pose_eval_{name}")])
    print(f"\nDone. Outputs in {out}/:\n"
          f"  scene/           the sample scene (presim info {scene})\n"
          f"  drive/           recording.mcap (ROS 2 messages) + capture/ (re-importable)\n"
          f"  drive.rrd        global 3D view (open with: rerun {out / 'drive.rrd'})\n"
          f"  bop/             BOP dataset\n"
          f"  pose_eval_gt*/   evaluator reports (summary.md) on GT and noisy GT")
    return 0
