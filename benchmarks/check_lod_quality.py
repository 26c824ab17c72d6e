"""Level of detail vs warping every point, at reduced target sizes, leave-one-out on a saved scene.

Targets: every 10th frame from 5; each is rendered from all other frames (``Scene.subset``) at its own
pose with its intrinsics scaled to W x H, with ``lod_levels=0`` and with the default (3), and compared
with the real image area-downsampled to W x H (what a W x H camera integrates). Depth used: the
scene's refined depth when present (refined with all frames, the target included: the same for both
configurations, so the comparison is fair, the absolute PSNR slightly optimistic).

    NUMBA_NUM_THREADS=1 PYTHONPATH=. python benchmarks/check_lod_quality.py out/apc
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def main() -> int:
    from presim.capture.store import load_scene
    from presim.synthesis.renderer import RenderConfig, Renderer

    scene = load_scene(sys.argv[1])
    sizes = [tuple(int(x) for x in s.split("x")) for s in (sys.argv[2] if len(sys.argv) > 2 else "160x120,320x240").split(",")]
    n = len(scene)

    def psnr(a, b):
        return 10 * np.log10(255.0**2 / np.mean((a.astype(float) - b.astype(float)) ** 2))

    for w, h in sizes:
        res: dict[int, list[float]] = {0: [], 3: []}
        for t in range(5, n, 10):
            sub = scene.subset([j for j in range(n) if j != t])
            f = scene.frame(t)
            K = f.K.scaled(w, h)
            gt = cv2.resize(f.color, (w, h), interpolation=cv2.INTER_AREA)
            for lv in res:
                res[lv].append(psnr(Renderer(sub, RenderConfig(lod_levels=lv)).render(f.T_world_cam, K).color, gt))
        print(f"{w}x{h}: targets {len(res[0])}  PSNR lod_levels=0 {np.mean(res[0]):.2f} dB  "
              f"lod_levels=3 {np.mean(res[3]):.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
