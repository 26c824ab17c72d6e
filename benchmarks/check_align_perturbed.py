"""Perturbation check of ``presim align``: perturbed poses, refined, come back to the poses refined
from the unperturbed ones.

Every given pose of a saved scene is perturbed by a seeded random rigid motion of fixed size
(``--trans-m`` along a random direction, ``--rot-deg`` about a random axis), then ``align_poses`` runs
on the perturbed scene. The result is compared with the reference: the poses refined from the
unperturbed given poses (the scene's ``poses_refined.json``, or a fresh ``align_poses`` run with
``--realign``). Reported: ATE RMSE (after a rigid Horn/Umeyama fit, TUM definition) of the perturbed
start and of the refined result against the reference, the same over the frames refined in both runs
(the acceptance step keeps the *given* pose of frames it cannot improve measurably: the mocap pose in
the reference run, a perturbed one in the other), how many frames each run kept, and the median
per-frame change, plus time. ``--accept-t 0`` switches the acceptance step off for the perturbed run
(and for ``--realign``): the refinement's own repeatability.

Both runs use ``AlignConfig``'s defaults (as plain ``presim align --keep-unmatched``: appearance
neighbours and second pass on ``auto``) unless an option below overrides them; the reference read
from ``poses_refined.json`` must have been made by such a run (``presim align SCENE --keep-unmatched``).
The output says whether the auto rule fired in each run, with its measured noise / spacing ratio.

    python benchmarks/check_align_perturbed.py out/tum --trans-m 0.03 --rot-deg 2 --seed 0 \
        --json out/tum_perturbed.json

Target: refined-from-perturbed within 1 cm ATE of refined-from-unperturbed (docs/alignment.md).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


def perturb_poses(T: np.ndarray, trans_m: float, rot_deg: float, seed: int) -> np.ndarray:
    """Each pose moved by exactly ``trans_m`` along a random direction and turned by exactly ``rot_deg``
    about a random axis through the camera centre (seeded). Pure."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    n = len(T)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    R = Rotation.from_rotvec(a * np.radians(rot_deg)).as_matrix()
    out = np.array(T, dtype=np.float64, copy=True)
    out[:, :3, :3] = np.einsum("nij,njk->nik", R, out[:, :3, :3])
    out[:, :3, 3] += d * trans_m
    return out


def _auto(am: dict | None) -> dict | None:
    """The auto rule's decision in a run's statistics (None: explicit settings, or made before the rule)."""
    if am is None:
        return None
    return {k: am.get(k) for k in ("fired", "ratio", "noise_m", "spacing_m", "weak_frames",
                                   "appearance_neighbours", "rematch_rounds")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--trans-m", type=float, default=0.03)
    ap.add_argument("--rot-deg", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--realign", action="store_true",
                    help="refine the unperturbed given poses here instead of reading poses_refined.json")
    ap.add_argument("--accept-t", type=float, default=None,
                    help="AlignConfig.accept_t for the perturbed run (and --realign); 0 = no acceptance step")
    ap.add_argument("--appearance-neighbours", type=int, default=None,
                    help="AlignConfig.appearance_neighbours for the perturbed run (and --realign); the "
                         "reference should be refined with the same value (default: auto)")
    ap.add_argument("--rematch-rounds", type=int, default=None,
                    help="AlignConfig.rematch_rounds for the perturbed run (and --realign) (default: auto)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    common.setup()

    from presim.align.pipeline import AlignConfig, align_poses, pose_change
    from presim.capture.store import load_scene
    from presim.evaluation.poses import ate_rpe

    scene = load_scene(args.scene, poses="given")
    T_given = np.asarray(scene.T_world_cam, dtype=np.float64)
    cfg = AlignConfig(seed=args.seed, keep_unmatched=True)
    if args.accept_t is not None:
        cfg = replace(cfg, accept_t=args.accept_t)
    if args.rematch_rounds is not None:
        cfg = replace(cfg, rematch_rounds=args.rematch_rounds)
    if args.appearance_neighbours is not None:
        cfg = replace(cfg, appearance_neighbours=args.appearance_neighbours)
    t0 = time.perf_counter()
    if args.realign:
        r = align_poses(scene, cfg)
        T_ref, ref_status = r.T_world_cam, [f["status"] for f in r.stats["per_frame"]]
        ref_auto = r.stats.get("auto_matching")
    else:
        from presim.capture.store import read_refined_poses

        T_ref, prov = read_refined_poses(args.scene, scene.frame_ids)
        ref_status = [f.get("status", "refined") for f in prov.get("frames", [])] or ["refined"] * len(scene)
        ref_auto = prov.get("stats", {}).get("auto_matching")
    t_ref = time.perf_counter() - t0

    T_pert = perturb_poses(T_given, args.trans_m, args.rot_deg, args.seed)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    res = align_poses(replace(scene, T_world_cam=T_pert), cfg)
    t_align, cpu_align = time.perf_counter() - t0, time.process_time() - cpu0
    T_out = res.T_world_cam

    e_start = ate_rpe(T_ref, T_pert)
    e_out = ate_rpe(T_ref, T_out)
    e_given = ate_rpe(T_ref, T_given)
    dt, dr = pose_change(T_out, T_ref)
    out_status = [f["status"] for f in res.stats["per_frame"]]
    both = np.array([a == "refined" and b == "refined" for a, b in zip(ref_status, out_status)])
    out = {
        "scene": str(args.scene),
        "frames": len(scene),
        "perturbation": {"trans_m": args.trans_m, "rot_deg": args.rot_deg, "seed": args.seed},
        "ate_given_vs_reference_m": e_given.ate_rmse_m,
        "ate_perturbed_vs_reference_m": e_start.ate_rmse_m,
        "ate_refined_vs_reference_m": e_out.ate_rmse_m,
        "ate_refined_vs_reference_frames_refined_in_both_m": (ate_rpe(T_ref[both], T_out[both]).ate_rmse_m
                                                              if both.sum() >= 3 else None),
        "frames_refined_in_both": int(both.sum()),
        "reference_kept_given": int(sum(s != "refined" for s in ref_status)),
        "perturbed_kept_given": int(sum(s != "refined" for s in out_status)),
        "refined_vs_reference_median_m": float(np.median(dt)),
        "refined_vs_reference_median_deg": float(np.median(dr)),
        "refined_vs_reference_max_m": float(np.max(dt)),
        "reference_auto_matching": _auto(ref_auto),
        "perturbed_auto_matching": _auto(res.stats.get("auto_matching")),
        "target_m": 0.01,
        "met": bool(e_out.ate_rmse_m <= 0.01),
        "align_wall_s": t_align,
        "align_cpu_s": cpu_align,
        "reference_wall_s": t_ref,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    print(json.dumps(out, indent=1))
    common.write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
