"""Telea inpainting: the numba kernel (presim/synthesis/telea.py) vs cv2.inpaint, in one run.

Renders bench_render.py's trajectory (midpoints of consecutive captured views) with
``RenderConfig(fill_holes=False)`` and takes each frame's colour and hole mask, i.e. exactly what the
final fill receives. For every frame whose holes are at most ``--max-hole-frac`` of the image (the
frames where ``fill_method="auto"`` runs Telea; 0.02 by default, as ``fill.fill_holes``), both
implementations inpaint it ``--repeats`` times, alternating (cv2, numba, cv2, numba ...), so load
changes hit both. Prints per frame: hole pixels, the median ms of each, the ratio cv2 / numba, and
whether the outputs are equal (they must be: the script exits 1 otherwise); then the median over
frames of the ratio and of the microseconds per hole pixel.

    .venv/bin/python benchmarks/bench_telea.py                  # synthetic room, 640x480
    .venv/bin/python benchmarks/bench_telea.py --scene out/sample --size 640x480
    .venv/bin/python benchmarks/bench_telea.py --scene out/sample --size 640x480 --max-hole-frac 1 --json out/t.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_render import in_memory, trajectory  # noqa: E402
import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.store import load_scene  # noqa: E402
from presim.geometry import Intrinsics  # noqa: E402
from presim.synthesis.renderer import RenderConfig, Renderer  # noqa: E402
from presim.synthesis.telea import telea_inpaint  # noqa: E402
from presim.testing import rect_scene as S  # noqa: E402


def _median_ms(fn, repeats: int) -> tuple[float, np.ndarray]:
    out = fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return float(np.median(ts)), out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="a saved PreSim scene (presim sample-scene / import); default: the "
                    "synthetic room of bench_render.py")
    ap.add_argument("--size", default="640x480", help="output WxH (default 640x480)")
    ap.add_argument("--frames", type=int, default=20, help="trajectory frames rendered (default 20)")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per implementation and frame")
    ap.add_argument("--max-hole-frac", type=float, default=0.02, help="frames with more holes are skipped")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.lower().split("x"))
    if args.scene:
        scene = in_memory(load_scene(args.scene))
    else:
        scene = S.make_scene(S.room_rects(), S.orbit_poses(16, span_m=1.6), Intrinsics.from_fov(640, 480, 60.0))
    K = Intrinsics.from_fov(w, h, scene.intrinsics[0].hfov_deg)
    r = Renderer(scene, RenderConfig(fill_holes=False))
    rows, equal = [], True
    print(f"scene {args.scene or 'synthetic room'} {w}x{h}, load average at start {os.getloadavg()}")
    for k, T in enumerate(trajectory(scene, args.frames)):
        o = r.render(T, K)
        color, holes = o.color.copy(), ~o.valid
        n = int(holes.sum())
        if n == 0 or n > args.max_hole_frac * holes.size:
            continue
        cv_ms = nb_ms = 0.0
        cv_list, nb_list = [], []
        for _ in range(2):  # alternate the two, half the repeats each time
            m, a = _median_ms(lambda: cv2.inpaint(color, holes.view(np.uint8), 3, cv2.INPAINT_TELEA),
                              max(1, args.repeats // 2))
            cv_list.append(m)
            m, b = _median_ms(lambda: telea_inpaint(color, holes, 3), max(1, args.repeats // 2))
            nb_list.append(m)
        cv_ms, nb_ms = float(np.median(cv_list)), float(np.median(nb_list))
        same = bool(np.array_equal(a, b))
        equal &= same
        rows.append({"frame": k, "hole_px": n, "hole_frac": n / holes.size, "cv2_ms": cv_ms, "numba_ms": nb_ms,
                     "ratio": cv_ms / nb_ms, "equal": same})
        print(f"frame {k:3d}  holes {n:6d} px ({100 * n / holes.size:5.2f} %)  cv2 {cv_ms:7.2f} ms  "
              f"numba {nb_ms:7.2f} ms  x{cv_ms / nb_ms:4.2f}  {'equal' if same else 'DIFFERENT'}")
    if not rows:
        print("no frame with holes within --max-hole-frac")
        return 0
    summary = {
        "frames": len(rows), "ratio_median": float(np.median([x["ratio"] for x in rows])),
        "cv2_us_per_hole_px_median": float(np.median([1e3 * x["cv2_ms"] / x["hole_px"] for x in rows])),
        "numba_us_per_hole_px_median": float(np.median([1e3 * x["numba_ms"] / x["hole_px"] for x in rows])),
        "all_equal": equal,
    }
    print(f"{summary['frames']} frames: cv2 / numba median x{summary['ratio_median']:.2f}; per hole pixel "
          f"cv2 {summary['cv2_us_per_hole_px_median']:.2f} us, numba {summary['numba_us_per_hole_px_median']:.2f} us; "
          f"outputs {'all equal' if equal else 'DIFFER'}")
    if args.json:
        tmp = Path(args.json).with_suffix(".tmp")
        tmp.write_text(json.dumps({"args": vars(args), "frames": rows, "summary": summary}, indent=1))
        tmp.replace(args.json)
    return 0 if equal else 1


if __name__ == "__main__":
    sys.exit(main())
