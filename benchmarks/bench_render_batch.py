"""Batched rendering throughput: ``Renderer.render_batch`` on ``torch_batch`` (CUDA when present, else
CPU) for batch sizes B, against the numba per-frame core on the same poses in the same run.

Poses: midpoints of consecutive captured views, cycled to fill each batch. Steady state: every
configuration renders its batch once (views prepared, kernels compiled), then ``--repeats`` timed
calls; medians of frames/s (= B / seconds per call). The prepared script for a GPU machine:

    PYTHONPATH=. python benchmarks/bench_render_batch.py --scene out/apc --sizes 128x128,640x480 \\
        --batches 1,8,64 --json out/bench_render_batch.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="saved scene folder")
    ap.add_argument("--sizes", default="128x128,640x480")
    ap.add_argument("--batches", default="1,8,64")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--views", type=int, default=3, help="batch_views of torch_batch")
    ap.add_argument("--json")
    args = ap.parse_args()
    os.environ["PRESIM_NO_PROGRESS"] = "1"
    from presim.capture.store import load_scene
    from presim.geometry import Intrinsics, make_pose
    from presim.synthesis.renderer import RenderConfig, Renderer

    import torch

    scene = load_scene(args.scene)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    name = torch.cuda.get_device_name(0) if dev == "cuda" else "cpu"
    print(f"scene {args.scene}  torch device {name}  cpus {os.cpu_count()}  load average {os.getloadavg()}")
    T = scene.T_world_cam
    mids = [make_pose(T[i][:3, :3], (T[i][:3, 3] + T[i + 1][:3, 3]) / 2) for i in range(len(T) - 1)]
    res = {}
    rb = Renderer(scene, RenderConfig(backend="torch_batch", batch_views=args.views, reuse_move_m=0.0))
    rn = Renderer(scene, RenderConfig(reuse_move_m=0.0))
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.split("x"))
        K = Intrinsics.from_fov(w, h, scene.intrinsics[0].hfov_deg)
        for B in (int(b) for b in args.batches.split(",")):
            poses = np.stack([mids[k % len(mids)] for k in range(B)])
            out = {}
            for label, r in (("torch_batch", rb), ("numba per frame", rn)):
                r.render_batch(poses, K)  # warm-up: prepare views, compile
                if dev == "cuda":
                    torch.cuda.synchronize()
                ts = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    r.render_batch(poses, K)
                    if dev == "cuda":
                        torch.cuda.synchronize()
                    ts.append(time.perf_counter() - t0)
                out[label] = B / statistics.median(ts)
            res[f"{size} B={B}"] = {"torch_batch_fps": out["torch_batch"], "numba_fps": out["numba per frame"],
                                    "ratio": out["torch_batch"] / out["numba per frame"], "device": name}
            print(f"{size:9s} B={B:3d}  torch_batch {out['torch_batch']:8.1f} frames/s   numba per frame "
                  f"{out['numba per frame']:7.1f} frames/s   ratio x{out['torch_batch'] / out['numba per frame']:.2f}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"results": res, "device": name}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
