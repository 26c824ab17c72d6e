"""``presim align`` (pose refinement, thesis §5.3.3) and ``presim eval-poses`` (ATE / RPE)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("align", help="refine the camera poses of a scene (local-to-global RGB-D bundle adjustment)",
                       description="Writes SCENE/poses_refined.json beside the given poses (never changed); "
                                   "render, eval-views, drive and gen-bop then use the refined poses unless "
                                   "given --scene-poses given. Atomic: an interrupted run leaves the scene as it was.")
    p.add_argument("scene", type=Path, help="saved scene folder")
    p.add_argument("--seed", type=int, default=0, help="key-pose and RANSAC seed (same seed = same poses)")
    p.add_argument("--max-group", type=int, default=10, help="poses per local group (thesis: 10)")
    p.add_argument("--features", type=int, default=2000, help="SIFT features per image (default 2000)")
    p.add_argument("--neighbours", type=int, default=6,
                   help="nearest frames each frame is matched to for the joint pass (default 6; 0 = none)")
    p.add_argument("--appearance-neighbours", type=_auto_int, default=None, metavar="K|auto",
                   help="frames most similar in appearance (bag of SIFT words, pose-free) each frame is also "
                        "matched to for the joint pass (0 = none). Default auto: none, unless the first pass "
                        "measures the given poses too noisy for neighbours chosen by camera-centre distance "
                        "(relative centre noise > --auto-noise-ratio x the centre spacing; then 6, and the "
                        "matching is done again; the output says so, with the numbers)")
    p.add_argument("--rematch-rounds", type=_auto_int, default=None, metavar="N|auto",
                   help="second matching pass for frames left unconnected or weakly connected, gate grown "
                        "to their pose uncertainty, at most this many rounds (0 = off). Default auto: 0, or 3 "
                        "when the rule above fires")
    p.add_argument("--auto-noise-ratio", type=float, default=0.25, metavar="R",
                   help="the auto rule fires when the relative camera-centre noise the first pass measures "
                        "exceeds this fraction of the distance to the --neighbours-th nearest centre "
                        "(default 0.25, docs/alignment.md)")
    p.add_argument("--pose-sigma-deg", type=float, default=None,
                   help="stated noise of the given poses (1 sigma per axis, degrees; with --pose-sigma-cm): "
                        "every matching gate grows to it (default: fixed 80 px gate, second pass measured)")
    p.add_argument("--pose-sigma-cm", type=float, default=None, help="as --pose-sigma-deg, camera centres (cm)")
    p.add_argument("--no-joint", action="store_true", help="thesis stages only (local + global key poses)")
    p.add_argument("--depth-residuals", action=argparse.BooleanOptionalAction, default=False,
                   help="also fit the depth residuals (RGB-D, beyond the thesis; default off: reprojection only, "
                        "as the thesis, measured better on the real captures, docs/alignment.md)")
    p.add_argument("--keep-unmatched", action="store_true",
                   help="keep the given pose of frames no match connects (default: error naming them)")
    p.add_argument("--accept-t", type=float, default=3.0,
                   help="a frame keeps its given pose unless the refined poses lower its reprojection "
                        "residuals by more than this many standard errors (default 3; 0 = accept all)")
    p.add_argument("--min-frame-obs", type=int, default=30,
                   help="frames with fewer verified observations keep their given pose (default 30)")
    p.add_argument("--from", dest="start", choices=("given", "refined"), default="given",
                   help="start from the given poses (default) or from existing refined ones")
    p.add_argument("--overwrite", action="store_true", help="replace existing refined poses")
    p.add_argument("--json", type=Path, default=None, help="also write the statistics here")
    p.set_defaults(func=_align)

    e = sub.add_parser("eval-poses", help="ATE / RPE of a scene's poses against a reference trajectory",
                       description="Reference: a TUM trajectory file (matched by timestamp, interpolated) or a "
                                   "saved scene / capture folder with poses (matched by frame id). TUM benchmark "
                                   "definitions; ATE after a rigid (or --similarity) alignment.")
    e.add_argument("scene", type=Path, help="saved scene folder")
    e.add_argument("--reference", type=Path, required=True, help="TUM trajectory file, scene or capture folder")
    e.add_argument("--scene-poses", choices=("auto", "given", "refined"), default="auto",
                   help="which poses of SCENE to score (default: refined when present)")
    e.add_argument("--similarity", action="store_true", help="also fit a scale (similarity alignment)")
    e.add_argument("--delta", type=int, default=1, help="RPE frame offset (default 1)")
    e.add_argument("--json", type=Path, default=None, help="write the metrics as JSON here")
    e.set_defaults(func=_eval_poses)


def _auto_int(s: str) -> int | None:
    """``auto`` -> None, else a non-negative integer (argparse type)."""
    if s == "auto":
        return None
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a non-negative integer, got {s!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a non-negative integer, got {s!r}")
    return v


def _align(args) -> int:
    import numpy as np

    from presim.align import AlignConfig, align_poses
    from presim.align.bundle import BAConfig
    from presim.align.features import FeatureConfig
    from presim.align.grouping import GroupConfig
    from presim.capture.store import REFINED_POSES_FILE, load_scene, save_refined_poses
    from presim.io_utils import atomic_write_json

    scene = load_scene(args.scene, poses=args.start)
    if (args.scene / REFINED_POSES_FILE).is_file() and not args.overwrite:
        raise FileExistsError(f"{args.scene / REFINED_POSES_FILE}: already exists (pass --overwrite to recompute)")
    if not args.auto_noise_ratio >= 0:
        raise ValueError(f"--auto-noise-ratio: must be >= 0, got {args.auto_noise_ratio}")
    if (args.pose_sigma_deg is None) != (args.pose_sigma_cm is None):
        raise ValueError("--pose-sigma-deg and --pose-sigma-cm go together (state both or neither)")
    cfg = AlignConfig(features=FeatureConfig(max_features=args.features), grouping=GroupConfig(max_group=args.max_group),
                      ba=BAConfig(use_depth=args.depth_residuals), joint=not args.no_joint,
                      joint_neighbours=args.neighbours, keep_unmatched=args.keep_unmatched, seed=args.seed,
                      accept_t=args.accept_t, min_frame_obs=args.min_frame_obs,
                      appearance_neighbours=args.appearance_neighbours, rematch_rounds=args.rematch_rounds,
                      auto_noise_ratio=args.auto_noise_ratio,
                      pose_sigma_deg=args.pose_sigma_deg,
                      pose_sigma_m=None if args.pose_sigma_cm is None else args.pose_sigma_cm / 100)
    res = align_poses(scene, cfg, log=lambda s: print(s, file=sys.stderr))
    st = res.stats
    prov = {"command": "presim align", "started_from": scene.poses_source, "seed": args.seed,
            "stats": {k: v for k, v in st.items() if k not in ("per_frame_change", "per_frame")},
            "frames": st["per_frame"]}
    out = save_refined_poses(args.scene, res.T_world_cam, scene.frame_ids, prov)
    b, a = st["transfer_px_before"], st["transfer_px_after"]
    am = st.get("auto_matching")
    if am is not None:
        print(("auto matching FIRED (given poses too noisy for distance neighbours): " if am["fired"] else
               "auto matching not needed: ") + am["message"] +
              f"; {am['weak_frames']} frame(s) weakly or not connected after the first pass; used "
              f"{am['appearance_neighbours']} appearance neighbours, {am['rematch_rounds']} second-pass round(s)")
    print(f"{args.scene}: {st['frames']} frames, {st['groups']} groups, {st['matches']} verified matches")
    print(f"feature transfer error median {b['median']:.2f} -> {a['median']:.2f} px, "
          f"depth residual median {st['depth_res_m_before']['median'] * 1000:.1f} -> "
          f"{st['depth_res_m_after']['median'] * 1000:.1f} mm")
    print(f"cameras moved median {st['change_m']['median'] * 100:.2f} cm / {st['change_deg']['median']:.2f} deg "
          f"(p90 {st['change_m']['p90'] * 100:.2f} cm / {st['change_deg']['p90']:.2f} deg), {st['time_s']['total']:.1f} s")
    for reason, ids in st["kept_given"].items():
        print(f"kept the given pose of {len(ids)} frame(s), {reason.removeprefix('given: ')}: "
              f"{', '.join(ids[:10])}" + (f" and {len(ids) - 10} more" if len(ids) > 10 else ""))
    n_ref = sum(r["status"] == "refined" for r in st["per_frame"])
    sig = [r["sigma_trans_m"] for r in st["per_frame"] if "sigma_trans_m" in r]
    print(f"refined {n_ref} of {st['frames']} frame(s)" + (
        f"; pose uncertainty (1 sigma, relative to the frames held fixed) median {np.median(sig) * 1000:.2f} mm, "
        f"max {max(sig) * 1000:.2f} mm (per frame: presim info --json)" if sig else ""))
    print(f"wrote {out}")
    if args.json is not None:
        atomic_write_json(args.json, st)
    return 0


def _reference_poses(ref: Path, scene) -> tuple:
    """(indices into scene, reference poses) matched by stamp (TUM file) or frame id (folder)."""
    import numpy as np

    from presim.evaluation.poses import match_by_stamp
    from presim.formats.tum import read_tum_rows

    if not ref.exists():
        raise FileNotFoundError(f"{ref}: reference not found")
    if ref.is_file():
        st, rows = read_tum_rows(ref)
        return match_by_stamp(scene.stamps_s, st, rows)
    from presim.capture.store import is_scene_dir, load_scene

    if is_scene_dir(ref):
        other = load_scene(ref, poses="given")
    elif (ref / "groundtruth.txt").is_file():
        st, rows = read_tum_rows(ref / "groundtruth.txt")
        return match_by_stamp(scene.stamps_s, st, rows)
    else:
        from presim.capture.importers import import_capture

        other = import_capture(ref, align_floor=False)
    pos = {f: i for i, f in enumerate(other.frame_ids)}
    idx = np.array([i for i, f in enumerate(scene.frame_ids) if f in pos], dtype=int)
    return idx, np.asarray(other.T_world_cam)[[pos[scene.frame_ids[i]] for i in idx]]


def _eval_poses(args) -> int:
    from presim.capture.store import load_scene
    from presim.evaluation.poses import ate_rpe
    from presim.io_utils import atomic_write_json

    scene = load_scene(args.scene, poses=args.scene_poses)
    idx, T_ref = _reference_poses(args.reference, scene)
    if len(idx) < 3:
        raise ValueError(f"{args.reference}: only {len(idx)} of the scene's {len(scene)} frames match the reference "
                         "(by timestamp within the reference's range, or by frame id)")
    err = ate_rpe(T_ref, scene.T_world_cam[idx], similarity=args.similarity, delta=args.delta)
    out = {**err.to_json(), "scene_poses": scene.poses_source, "reference": str(args.reference), "delta": args.delta}
    print(f"{args.scene} ({scene.poses_source} poses) vs {args.reference}: {err.frames_matched} frames matched, "
          f"{err.alignment} alignment")
    print(f"ATE RMSE {err.ate_rmse_m * 100:.2f} cm   RPE (delta {args.delta}) {err.rpe_trans_m * 100:.2f} cm / "
          f"{err.rpe_rot_deg:.3f} deg")
    if args.json is not None:
        atomic_write_json(args.json, out)
        print(f"wrote {args.json}")
    return 0
