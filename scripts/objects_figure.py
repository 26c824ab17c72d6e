"""Figure for docs/objects.md: reconstructed models and real-split visible masks over three frames.

    python scripts/objects_figure.py SCENE BOP_OUT OUT.png
"""

import json
import sys
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

COLORS = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180]])


def main(scene: str, bop: str, out: str) -> None:
    import open3d as o3d

    hdr = json.loads((Path(scene) / "scene.json").read_text())
    objs = hdr["objects"]
    sdir = Path(bop) / "real" / "000000"
    gt = json.loads((sdir / "scene_gt.json").read_text())
    ims = sorted(gt, key=int)
    pick = [ims[0], ims[len(ims) // 2], ims[-1]]
    fig, ax = plt.subplots(2, max(3, len(objs)), figsize=(4 * max(3, len(objs)), 7))
    for a in ax.ravel():
        a.axis("off")
    for c, im in enumerate(pick):
        rgb = cv2.cvtColor(cv2.imread(str(sdir / "rgb" / f"{int(im):06d}.png")), cv2.COLOR_BGR2RGB).astype(float)
        for k, g in enumerate(gt[im]):
            m = cv2.imread(str(sdir / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), 0) > 0
            col = COLORS[(g["obj_id"] - 1) % len(COLORS)]
            rgb[m] = 0.45 * rgb[m] + 0.55 * col
        ax[0, c].imshow(rgb.astype(np.uint8))
        ax[0, c].set_title(f"image {im}: visible masks")
    for c, o in enumerate(objs):
        pc = o3d.io.read_point_cloud(str(Path(scene) / o["points_path"]))
        p, col = np.asarray(pc.points), np.asarray(pc.colors)
        ax[1, c].scatter(p[:, 0], p[:, 2], c=col, s=0.3)
        ax[1, c].set_aspect("equal")
        ax[1, c].set_title(f"obj {o['obj_id']}: {len(p)} pts, x-z view")
    fig.tight_layout()
    fig.savefig(out, dpi=70)


if __name__ == "__main__":
    main(*sys.argv[1:4])
