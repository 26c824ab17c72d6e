"""Benchmark one training step of the quick recipe on a real BOP folder, in CPU time.

Baseline (same run): the previous quick recipe's settings on the same code — instances read from
the image files every step (no cache), 64 px crop, batch 8, 200 model points, ADD-S loss, EdgeConv
convolving the explicit edge tensor (``EdgeConv.forward_reference``). The quick recipe: the
defaults of ``TrainConfig`` (cached instances, 32 px crop, batch 16, 100 model points,
symmetry-transform loss, EdgeConv computed per point then gathered). Both include the data loading
(DataLoader iteration, collation) and the optimiser step. CPU time (``time.process_time``) is
reported because wall time on a shared machine is inflated by other processes; run with
``--threads 1`` for the most stable number (2 threads add a little CPU time for synchronisation).

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_posenet_recipe.py out/bop_train --model cgaf
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.pose.nets import models as models_mod
from presim.pose.nets import train as tr
from presim.pose.nets.loss import LossConfig


def _measure(dataset: str, cfg: tr.TrainConfig, steps: int) -> dict:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="BOP folder with a train split")
    ap.add_argument("--model", default="cgaf", choices=models_mod.ARCHS)
    ap.add_argument("--steps", type=int, default=10, help="timed steps per setting (median reported)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
