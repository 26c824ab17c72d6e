"""Benchmark ADD-S (and ADD) over many poses of one 2k-point model.

Baseline: the numpy reference ``presim.pose.metrics.adi`` (bop_toolkit's definition: one KD-tree
over the estimate-posed points per evaluation), timed on ``--ref-evals`` poses and reported per
evaluation. Fast paths, timed on ``--n-evals`` poses: the batched KD-tree over the model
(``adi_batch_kdtree``), the numba grid index (``NNGrid``, build time reported apart), torch cdist
(CPU on a subset; CUDA when ``--device cuda``). Each is warmed up, repeated, and the median printed
with its ratio to the reference measured in the same run.

    .venv/bin/python benchmarks/bench_metrics.py [--n-evals 100000] [--n-points 2000] [--device cuda]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)

LMO_MODEL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lmo_scene000002" / "models_eval" / "obj_000008.ply"


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-evals", type=int, default=100_000)
    ap.add_argument("--n-points", type=int, default=2000)
    ap.add_argument("--ref-evals", type=int, default=300, help="poses for the (slow) numpy reference")
    ap.add_argument("--torch-evals", type=int, default=100, help="poses for torch on CPU")
    ap.add_argument("--kd-evals", type=int, default=10_000, help="poses for the batched KD-tree")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import torch

    from presim.pose import metrics, metrics_torch as mt
    from presim.pose.nn_grid import NNGrid, adi_batch_kdtree

    rng = np.random.default_rng(args.seed)
    if LMO_MODEL.is_file():
        from presim.formats.bop import MM_TO_M
        from presim.formats.ply import read_ply
        pts_all = read_ply(LMO_MODEL).scaled(MM_TO_M).vertices
        src = f"LM-O driller models_eval ({len(pts_all)} pts)"
    else:
        pts_all = rng.normal(0, 0.05, (10000, 3)) * [2.0, 0.6, 1.6]
        src = "synthetic gaussian cloud"
    pts = pts_all[rng.choice(len(pts_all), min(args.n_points, len(pts_all)), replace=False)]
    E = args.n_evals
    R_g = Rotation.random(E, random_state=args.seed).as_matrix()
    t_g = rng.normal(0, 0.1, (E, 3)) + [0, 0, 1.0]
    # Plausible estimates: ~6 deg and ~1.7 cm off (typical of the LM-O third-party estimates).
    R_e = R_g @ Rotation.from_rotvec(rng.normal(0, 0.06, (E, 3))).as_matrix()
    t_e = t_g + rng.normal(0, 0.01, (E, 3))
    print(f"model: {src}, {len(pts)} points; {E} poses; torch threads {torch.get_num_threads()}")

    n_ref = min(args.ref_evals, E)
    ref_vals = None

    def ref():
        nonlocal ref_vals
        ref_vals = np.array([metrics.adi(R_e[i], t_e[i], R_g[i], t_g[i], pts) for i in range(n_ref)])

    ref()  # warm-up
    t_ref = _median_time(ref, args.repeats) / n_ref
    rows = [("numpy reference adi (tree per pose)", n_ref, t_ref, None)]

    out = {}

    n_kd = min(args.kd_evals, E)

    def kd():
        out["kd"] = adi_batch_kdtree(pts, R_e[:n_kd], t_e[:n_kd], R_g[:n_kd], t_g[:n_kd])

    adi_batch_kdtree(pts, R_e[:100], t_e[:100], R_g[:100], t_g[:100])
    t_kd = _median_time(kd, args.repeats) / n_kd
    rows.append(("batched KD-tree over the model", n_kd, t_kd, np.abs(out["kd"][:n_ref] - ref_vals[:n_kd]).max()))

    t0 = time.perf_counter()
    grid = NNGrid(pts)
    t_build = time.perf_counter() - t0
    grid.adi(R_e[:100], t_e[:100], R_g[:100], t_g[:100])  # numba compile / warm-up

    def gr():
        out["grid"] = grid.adi(R_e, t_e, R_g, t_g)

    t_grid = _median_time(gr, args.repeats) / E
    rows.append((f"numba grid index (build {t_build:.2f} s, {grid.mean_candidates:.0f} cand/cell)", E, t_grid,
                 np.abs(out["grid"][:n_ref] - ref_vals).max()))

    n_t = min(args.torch_evals, E) if args.device == "cpu" else E
    b = mt.as_batch(R_e[:n_t], t_e[:n_t], R_g[:n_t], t_g[:n_t], device=args.device)
    P = torch.as_tensor(pts, device=args.device)

    def tc():
        out["torch"] = mt.adi(*b, P).cpu().numpy()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    tc()
    t_torch = _median_time(tc, args.repeats) / n_t
    rows.append((f"torch cdist ({args.device})", n_t, t_torch, np.abs(out["torch"][:n_ref] - ref_vals[:n_t]).max()))

    # ADD for scale: numpy reference vs batched torch.
    def add_ref():
        for i in range(n_ref):
            metrics.add(R_e[i], t_e[i], R_g[i], t_g[i], pts)

    t_add_ref = _median_time(add_ref, args.repeats) / n_ref
    bt = mt.as_batch(R_e, t_e, R_g, t_g, device=args.device)
    t_add = _median_time(lambda: mt.add(*bt, P).cpu(), args.repeats) / E

    print(f"\n{'ADD-S method':58s} {'poses':>7s} {'us/pose':>9s} {'100k poses':>11s} {'vs ref':>8s} {'max |diff|':>11s}")
    for name, n, t, diff in rows:
        d = "-" if diff is None else f"{diff:.1e}"
        print(f"{name:58s} {n:7d} {t * 1e6:9.1f} {t * 1e5:10.1f}s {t_ref / t:7.1f}x {d:>11s}")
    print(f"\n{'ADD method':58s} {'us/pose':>9s} {'100k poses':>11s} {'vs ref':>8s}")
    print(f"{'numpy reference add':58s} {t_add_ref * 1e6:9.1f} {t_add_ref * 1e5:10.1f}s {1.0:7.1f}x")
    print(f"{'torch batched add (' + args.device + ')':58s} {t_add * 1e6:9.1f} {t_add * 1e5:10.1f}s {t_add_ref / t_add:7.1f}x")


if __name__ == "__main__":
    main()
