"""Benchmark the pose networks: inference ms per object and one training step, quick or full sizes.

Baseline: DenseFusion at the same sizes, measured in the same run; C/G-AF and C/G-AF without
attention are reported as medians and as ratios to it. Random inputs of the recipe's shapes (crop
``--crop`` px, ``--points`` points, batch ``--batch``; defaults: the quick recipe's); each is warmed
up, then repeated. Wall time: on a shared machine prefer ``benchmarks/bench_posenet_recipe.py``
(CPU time, real data, data loading included).

    .venv/bin/python benchmarks/bench_posenets.py [--points 128] [--full-size] [--device cuda]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.pose.nets.loss import pose_loss
from presim.pose.nets.models import ARCHS, ModelConfig, PoseNet, best_pose


def _median(fn, repeats: int, device: str) -> float:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=128)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--crop", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--full-size", action="store_true")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
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

        res[arch] = (_median(infer, a.repeats, dev), _median(step, a.repeats, dev))
    base = res["densefusion"]
    print(f"device {dev}, threads {torch.get_num_threads()}, points {N}, batch {B}, "
          f"{'full' if a.full_size else 'quick'} sizes")
    for arch, (ti, ts) in res.items():
        print(f"{arch:12s} inference {1000 * ti:7.1f} ms/object (x{ti / base[0]:.2f} DenseFusion)   "
              f"train step {1000 * ts:7.1f} ms/batch (x{ts / base[1]:.2f})")


if __name__ == "__main__":
    main()
