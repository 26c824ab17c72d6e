"""The crack pass alone, on real inputs: three-kernel packed chain vs the row-band fusion, one run.

The inputs are captured from the renderer: for each frame of bench_render.py's trajectory (midpoints
of consecutive captured views), every view the adaptive loop warps is recorded with its warped
layers and its ``replace`` mask. Then ``composite.filtered_composite_packed`` and
``composite.filtered_composite_banded`` are run on all of them, in alternating repetitions (so load
changes on a shared machine hit both), and the median CPU ms per frame (process time, all threads)
is printed with the ratio; the outputs are checked equal on the pixels each input asks for.
With ``--base DIR`` the row-band fusion of another source tree (its
``presim/synthesis/composite.py``, e.g. ``git archive`` of an earlier commit) runs in the same
alternation, and its ratio to this tree's is printed too.

    NUMBA_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_crack_kernels.py \\
        --scene /work/scenes/apc_r --sizes 640x480,256x256,128x128 [--base /tmp/base_tree]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_render import trajectory  # noqa: E402
import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.store import load_scene  # noqa: E402
from presim.geometry import Intrinsics  # noqa: E402
from presim.synthesis import core  # noqa: E402
from presim.synthesis.composite import filtered_composite_banded, filtered_composite_packed  # noqa: E402
from presim.synthesis.renderer import RenderConfig, Renderer  # noqa: E402


def capture_inputs(scene, K: Intrinsics, poses: np.ndarray) -> list:
    """(layers depth, layers colour, replace or None) of every view warped for ``poses``."""
    got = []

    def spy(view, T, K_, cfg, replace, ws):
        out = core.view_image_numba(view, T, K_, cfg, replace, ws)
        got.append((ws.layers.depth_m.copy(), ws.layers.color.copy(), None if replace is None else replace.copy()))
        return out

    r = Renderer(scene, RenderConfig())
    r._backend = core.SynthesisBackend("numba", spy, core._host_view, core._no_device)
    for T in poses:
        r.render(T, K)
    return got


def load_base_banded(tree: Path):
    """``filtered_composite_banded`` of another source tree's ``presim/synthesis/composite.py``,
    loaded as a separate module (its own imports resolve to this tree's ``presim``)."""
    path = tree / "presim" / "synthesis" / "composite.py"
    if not path.is_file():
        raise SystemExit(f"--base: {path} does not exist")
    spec = importlib.util.spec_from_file_location("base_composite", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod.filtered_composite_banded


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--sizes", default="640x480,256x256,128x128")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--base", help="another source tree: also time its filtered_composite_banded")
    args = ap.parse_args()
    import numba

    print(f"numba threads: {numba.get_num_threads()}  load average at start: {os.getloadavg()}")
    scene = load_scene(args.scene)
    poses = trajectory(scene, args.frames)
    fns = {"packed": filtered_composite_packed, "banded": filtered_composite_banded}
    if args.base:
        fns["base"] = load_base_banded(Path(args.base))
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.split("x"))
        K = Intrinsics.from_fov(w, h, scene.intrinsics[0].hfov_deg)
        inputs = capture_inputs(scene, K, poses)
        for d, c, rep in inputs:  # same output where defined (and compiled before timing)
            (pd, pc), *rest = (f(d, c, rep) for f in fns.values())
            m = np.ones(pd.shape, bool) if rep is None else rep
            if not all(np.array_equal(pd[m], bd[m]) and np.array_equal(pc[m], bc[m]) for bd, bc in rest):
                print(f"{size}: OUTPUTS DIFFER")
                return 1
        t = {k: [] for k in fns}
        for _ in range(args.repeats):
            for k, f in fns.items():
                c0 = time.process_time()
                for d, c, rep in inputs:
                    f(d, c, rep)
                t[k].append((time.process_time() - c0) / len(poses) * 1e3)
        med = {k: float(np.median(v)) for k, v in t.items()}
        print(f"{size:9s} views/frame {len(inputs) / len(poses):.1f}  CPU ms per frame: packed {med['packed']:.2f}  "
              f"banded {med['banded']:.2f}  ratio {med['packed'] / med['banded']:.2f}"
              + (f"  base banded {med['base']:.2f}  base/banded {med['base'] / med['banded']:.2f}" if "base" in med else "")
              + "  (outputs equal)")
    print(f"load average at end: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
