"""Command line of the reprojection check (:func:`presim.capture.reprojection.reprojection_mae`):
``python -m presim.capture.reprojection_check SRC TARGET:SOURCE ...`` prints the colour error of
each frame pair warped with the capture's poses against the no-motion baseline (docs/importers.md).
"""

from __future__ import annotations

import argparse

import numpy as np

from presim.capture.importers import import_capture
from presim.capture.reprojection import reprojection_mae
from presim.capture.store import is_scene_dir, load_scene

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """``python -m presim.capture.reprojection_check SRC TARGET:SOURCE ...``: MAE with poses vs no motion.

    SRC is a saved scene or any capture folder ``presim import`` reads; TARGET/SOURCE are frame ids
    (e.g. ``frame-000031``), bare frame numbers matched against the ids, or positions.
    """
    ap = argparse.ArgumentParser(prog="python -m presim.capture.reprojection_check", description=main.__doc__)
    ap.add_argument("src")
    ap.add_argument("pairs", nargs="+", help="TARGET:SOURCE")
    args = ap.parse_args(argv)
    if is_scene_dir(args.src):
        scene = load_scene(args.src)
    else:
        scene = import_capture(args.src, align_floor=False)

    def resolve(tok: str) -> int:
        if tok in scene.frame_ids:
            return scene.frame_ids.index(tok)
        for i, fid in enumerate(scene.frame_ids):
            digits = "".join(ch for ch in fid if ch.isdigit())
            if digits and int(digits) == int(tok):
                return i
        return int(tok)

    rows = []
    for p in args.pairs:
        t, s = (resolve(x) for x in p.split(":"))
        m1, c1 = reprojection_mae(scene, t, s)
        m0, _ = reprojection_mae(scene, t, s, use_poses=False)
        rows.append((m1, m0, c1))
        print(f"{scene.frame_ids[t]} <- {scene.frame_ids[s]}: MAE with poses {m1:6.2f}  no motion {m0:6.2f}  "
              f"coverage {c1:.3f}")
    r = np.array(rows)
    print(f"mean: MAE with poses {r[:, 0].mean():.2f}  no motion {r[:, 1].mean():.2f}  coverage {r[:, 2].mean():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
