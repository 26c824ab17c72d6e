"""Pose estimation costs: ADD-S / ADD metrics, the pose networks, one training step of the recipe.

Sub-commands, each against a baseline measured in the same run:

- ``metrics``: ADD-S (and ADD) over many poses of one 2k-point model (``../shared/data``'s LM-O
  driller when present, else a synthetic cloud). Baseline: the numpy reference
  ``presim.pose.metrics.adi`` (bop_toolkit's definition: one KD-tree over the estimate-posed points
  per evaluation) on ``--ref-evals`` poses. Fast paths: the batched KD-tree over the model
  (``adi_batch_kdtree``), the numba grid index (``NNGrid``, build time apart), torch cdist (CPU on a
  subset; CUDA with ``--device cuda``). Medians, ratios to the reference, max |difference|.
- ``nets``: inference ms per object and one training step of each pose network at the quick (or
  ``--full-size``) sizes on random inputs of the recipe's shapes; ratios to DenseFusion. Wall time:
  on a shared machine prefer ``recipe`` (CPU time, real data, data loading included).
- ``recipe DATASET``: one training step of the quick recipe on a real BOP folder, CPU time
  (``time.process_time``), data loading and the optimiser step included. Baseline: the slower
  settings on the same code (instances read from the image files every step, 64 px crop, batch 8,
  200 model points, ADD-S loss, EdgeConv on the explicit edge tensor: ``EdgeConv.forward_reference``).
  ``--threads 1`` gives the most stable number.

    python benchmarks/bench_pose.py metrics [--n-evals 100000] [--n-points 2000] [--device cuda]
    python benchmarks/bench_pose.py nets [--points 128] [--full-size] [--device cuda]
    OMP_WAIT_POLICY=PASSIVE python benchmarks/bench_pose.py recipe out/bop_train --model cgaf
    python benchmarks/bench_pose.py metrics --quick      # smoke run
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402

LMO_MODEL = common.LMO / "models_eval" / "obj_000008.ply"


def _median_time(fn, repeats: int) -> float:
    """Median wall seconds of ``repeats`` calls (no warm-up: the callers warm up)."""
    return common.median_ms(fn, repeats, warmup=0)[0] / 1e3


# ---- metrics -----------------------------------------------------------------------------------

def cmd_metrics(args) -> None:
    from scipy.spatial.transform import Rotation

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



# ---- nets --------------------------------------------------------------------------------------

def _median_synced(fn, repeats: int, device: str) -> float:
    """Median wall seconds after one warm-up call, CUDA synchronised around each call."""
    import torch

    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)



def cmd_nets(a) -> None:
    import torch

    from presim.pose.nets.loss import pose_loss
    from presim.pose.nets.models import ARCHS, ModelConfig, PoseNet, best_pose

    torch.manual_seed(0)
    S, N, B, dev = a.crop, a.points, a.batch, a.device
    res = {}
    for arch in ARCHS:
        cfg = ModelConfig.full(arch, 5) if a.full_size else ModelConfig(arch=arch, n_objects=5)
        net = PoseNet(cfg).to(dev)
        rgb1, pts1 = torch.randn(1, 3, S, S, device=dev), torch.randn(1, N, 3, device=dev) * 0.05 + 0.8
        ch1, oi1 = torch.randint(0, S * S, (1, N), device=dev), torch.zeros(1, dtype=torch.long, device=dev)

        @torch.no_grad()
        def infer():
            out = net.eval()(rgb1, pts1, ch1, oi1)
            R, t, _ = best_pose(out)
            for _ in range(cfg.refine_iters):
                R, t = net.refine(pts1, out.emb, oi1, R, t)

        rgb, pts = torch.randn(B, 3, S, S, device=dev), torch.randn(B, N, 3, device=dev) * 0.05 + 0.8
        ch, oi = torch.randint(0, S * S, (B, N), device=dev), torch.zeros(B, dtype=torch.long, device=dev)
        m = torch.randn(B, 100, 3, device=dev) * 0.05
        sym = torch.zeros(B, dtype=torch.bool, device=dev)
        opt = torch.optim.Adam(net.parameters(), lr=1e-4)

        def step():
            out = net.train()(rgb, pts, ch, oi)
            loss = pose_loss(out.R, out.t, out.conf, m, m + 0.8, sym).loss
            opt.zero_grad()
            loss.backward()
            opt.step()

        res[arch] = (_median_synced(infer, a.repeats, dev), _median_synced(step, a.repeats, dev))
    base = res["densefusion"]
    print(f"device {dev}, threads {torch.get_num_threads()}, points {N}, batch {B}, "
          f"{'full' if a.full_size else 'quick'} sizes")
    for arch, (ti, ts) in res.items():
        print(f"{arch:12s} inference {1000 * ti:7.1f} ms/object (x{ti / base[0]:.2f} DenseFusion)   "
              f"train step {1000 * ts:7.1f} ms/batch (x{ts / base[1]:.2f})")



# ---- recipe ------------------------------------------------------------------------------------

def _measure(dataset: str, cfg, steps: int) -> dict:
    import torch

    from presim.pose.nets import train as tr

    torch.manual_seed(0)
    t0 = time.process_time()
    task = tr._PoseTask(dataset, cfg)
    task.prepare(show_progress=False)
    setup = time.process_time() - t0
    net, opt = task.net, torch.optim.Adam(task.net.parameters(), lr=cfg.lr)
    loader = torch.utils.data.DataLoader(task.train_set, batch_size=cfg.batch_size, shuffle=True,
                                         generator=torch.Generator().manual_seed(0), num_workers=0, drop_last=True)
    it, ts = iter(loader), []
    for s in range(steps + 1):  # the first step is a warm-up
        c0 = time.process_time()
        batch = next(it)
        loss, _ = task.step(net, batch, s, 10 ** 9)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if s:
            ts.append(time.process_time() - c0)
    med = statistics.median(ts)
    return {"setup_s": setup, "step_s": med, "inst_ms": 1000 * med / cfg.batch_size}



def cmd_recipe(args) -> None:
    import torch

    from presim.pose.nets import models as models_mod
    from presim.pose.nets import train as tr
    from presim.pose.nets.loss import LossConfig

    torch.set_num_threads(args.threads)
    quick = tr.TrainConfig(model=args.model)
    old = replace(quick, batch_size=8, loss=LossConfig(symmetry="adds"),
                  data=replace(quick.data, cache=False, crop_px=64, n_model_points=200))
    fast_forward = models_mod.EdgeConv.forward
    models_mod.EdgeConv.forward = models_mod.EdgeConv.forward_reference
    try:
        b = _measure(args.dataset, old, args.steps)
    finally:
        models_mod.EdgeConv.forward = fast_forward
    q = _measure(args.dataset, quick, args.steps)
    print(f"{args.model}, {args.threads} thread(s), CPU time, median of {args.steps} steps incl. data loading")
    print(f"  baseline (previous recipe): {b['step_s'] * 1000:7.1f} ms/step (batch {old.batch_size}) "
          f"= {b['inst_ms']:6.2f} ms/instance; setup {b['setup_s']:.1f} s")
    print(f"  quick recipe              : {q['step_s'] * 1000:7.1f} ms/step (batch {quick.batch_size}) "
          f"= {q['inst_ms']:6.2f} ms/instance; setup incl. caching {q['setup_s']:.1f} s")
    print(f"  instances per CPU-second: {1000 / b['inst_ms']:.1f} -> {1000 / q['inst_ms']:.1f} "
          f"(x{b['inst_ms'] / q['inst_ms']:.2f})")
    n = quick.steps
    print(f"  quick recipe ({n} steps) estimate: {n * q['step_s'] / 60:.1f} CPU-min + setup")



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("metrics", help="ADD-S / ADD: numpy reference vs KD-tree, grid index, torch")
    p.add_argument("--n-evals", type=int, default=100_000)
    p.add_argument("--n-points", type=int, default=2000)
    p.add_argument("--ref-evals", type=int, default=300, help="poses for the (slow) numpy reference")
    p.add_argument("--torch-evals", type=int, default=100, help="poses for torch on CPU")
    p.add_argument("--kd-evals", type=int, default=10_000, help="poses for the batched KD-tree")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="smoke run: 200 poses of 300 points, 1 repeat")
    p = sub.add_parser("nets", help="pose networks: inference and training step vs DenseFusion")
    p.add_argument("--points", type=int, default=128)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--crop", type=int, default=32, help="crop side, px (a multiple of 32)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--full-size", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quick", action="store_true", help="smoke run: 32 points, batch 2, 1 repeat")
    p = sub.add_parser("recipe", help="one training step of the quick recipe vs the slower settings, CPU time")
    p.add_argument("dataset", help="BOP folder with a train split")
    p.add_argument("--model", default="cgaf")
    p.add_argument("--steps", type=int, default=10, help="timed steps per setting (median reported)")
    p.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if getattr(args, "quick", False):
        if args.cmd == "metrics":
            args.n_evals, args.n_points, args.ref_evals, args.torch_evals, args.kd_evals, args.repeats = \
                200, 300, 20, 20, 200, 1
        else:
            args.points, args.batch, args.crop, args.repeats = 32, 2, 32, 1
    common.setup()
    {"metrics": cmd_metrics, "nets": cmd_nets, "recipe": cmd_recipe}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
