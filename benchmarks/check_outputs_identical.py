"""Fingerprint of deterministic synthesis / reprojection / refinement outputs, to prove a refactor
changed nothing: run with ``--save DIR`` before the change and ``--compare DIR`` after it; arrays are
compared for exact (byte) equality and every differing array is named with its count of differing
elements.

What it renders (all deterministic):
- the built-in sample scene (320x240, 16 frames, built once into the benchmarks' cache folder, or
  into ``--work``) and ``../shared/data/apc_cardboard_bin_kinfu50`` relative to the repository root
  (imported with ``import_capture``, no floor alignment, raw depth): three
  midpoint poses each, with the numba backend under several RenderConfigs (defaults, fixed views,
  one layer, plain median, no crack filter, no fill, max_zoom on a 2x target), at a half and a
  quarter target size (levels of detail), and the torch (CPU) and reference backends at a reduced
  target size (the reference is slow);
- ``capture.reprojection.forward_warp`` / ``reprojection_mae`` on apc frame pairs;
- ``depth.refine.refine_depth`` (numba and reference) on a tiny two-plane case.

    python benchmarks/check_outputs_identical.py --save /tmp/fp_before
    python benchmarks/check_outputs_identical.py --compare /tmp/fp_before
    python benchmarks/check_outputs_identical.py --save /tmp/fp --parts refine     # seconds: a smoke run

``--forward-color`` renders without backward colour sampling (trees before it have no such stage);
``--thesis-loop`` renders with ``min_view_gain=0`` (the thesis's adaptive loop; the default stops it at
diminishing returns): compare kernels with a tree whose default has no such stop.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402

APC = common.APC

CONFIGS = {
    "default": {},
    "fixed2": {"fixed_views": 2},
    "layers1": {"num_layers": 1},
    "median": {"crack_filter": "median"},
    "nocrack": {"crack_filter": "none"},
    "nofill": {"fill_holes": False},
    "overlap_greedy": {"view_order": "overlap", "next_view_fill_frac": 1.0},
}


def _midpoints(T: np.ndarray, pairs: list[tuple[int, int]]) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation, Slerp

    out = []
    for a, b in pairs:
        s = Slerp([0.0, 1.0], Rotation.from_matrix(T[[a, b], :3, :3]))
        M = np.eye(4)
        M[:3, :3] = s(0.5).as_matrix()
        M[:3, 3] = 0.5 * (T[a, :3, 3] + T[b, :3, 3])
        out.append(M)
    return out


EXTRA: dict = {}
"""Fields added to every RenderConfig of the fingerprint (``--thesis-loop``)."""


def _render_scene(tag: str, scene, pairs, out: dict) -> None:
    from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

    K = scene.intrinsics[0]
    poses = _midpoints(scene.T_world_cam, pairs)
    for name, kw in CONFIGS.items():
        r = Renderer(scene, RenderConfig(**{**EXTRA, **kw}))
        for i, T in enumerate(poses):
            rgbd = r.render(T, K)
            key = f"{tag}/{name}/{i}"
            out[key + "/color"] = rgbd.color
            out[key + "/depth"] = rgbd.depth_m
            out[key + "/valid"] = rgbd.valid
            out[key + "/src"] = rgbd.source_view
            out[key + "/views"] = np.asarray(r.last.views, np.int64)
            out[key + "/holes"] = np.asarray(r.last.hole_frac_per_view, np.float64)
    # A target at twice the capture's focal length (zoom path: internal render + upsampling).
    r = Renderer(scene, RenderConfig(**EXTRA))
    K2 = K.scaled(2 * K.width, 2 * K.height)
    rgbd = r.render(poses[0], K2)
    out[f"{tag}/zoom/color"] = rgbd.color
    out[f"{tag}/zoom/depth"] = rgbd.depth_m
    # Small targets with the default numba pipeline: coarser levels of detail (pooled views), one
    # thread, the fused hole scores of the adaptive loop.
    Ks = K.scaled(K.width // 4, K.height // 4)
    r = Renderer(scene, RenderConfig(**EXTRA))
    for i, T in enumerate(poses):
        for size, Kt in (("quarter", Ks), ("half", K.scaled(K.width // 2, K.height // 2))):
            rgbd = r.render(T, Kt)
            key = f"{tag}/small-{size}/{i}"
            out[key + "/color"] = rgbd.color
            out[key + "/depth"] = rgbd.depth_m
            out[key + "/views"] = np.asarray(r.last.views, np.int64)
            out[key + "/levels"] = np.asarray(r.last.lod_levels, np.int64)
    # torch (CPU) and reference backends on a small target (the reference loops in Python).
    for backend in ("torch", "reference"):
        try:
            r = Renderer(scene, RenderConfig(max_views=3, max_zoom=100.0, **EXTRA),
                         PerfConfig(backend=backend, torch_device="cpu" if backend == "torch" else None))
        except ImportError as e:  # torch not installed
            print(f"{tag}: {backend} skipped ({e})")
            continue
        rgbd = r.render(poses[0], Ks)
        out[f"{tag}/{backend}/color"] = rgbd.color
        out[f"{tag}/{backend}/depth"] = rgbd.depth_m
        out[f"{tag}/{backend}/views"] = np.asarray(r.last.views, np.int64)


def _reprojection(scene, tag: str, out: dict) -> None:
    from presim.capture.reprojection import forward_warp, reprojection_mae
    from presim.geometry import compose, invert

    for t, s in ((8, 7), (20, 24), (31, 30)):
        if max(t, s) >= len(scene):
            continue
        ft, fs = scene.frame(t), scene.frame(s)
        c, d = forward_warp(fs.color, fs.depth_m, fs.K, ft.K, compose(invert(ft.T_world_cam), fs.T_world_cam))
        out[f"{tag}/fwarp/{t}_{s}/color"] = c
        out[f"{tag}/fwarp/{t}_{s}/depth"] = d
        out[f"{tag}/fwarp/{t}_{s}/mae"] = np.asarray(reprojection_mae(scene, t, s), np.float64)


def _refine(out: dict) -> None:
    from presim.depth.refine import RefineConfig, RefView, refine_depth
    from presim.testing.two_planes import render_two_planes, two_plane_poses
    from presim.geometry import Intrinsics

    K = Intrinsics.from_fov(40, 30, 60.0)
    poses = two_plane_poses(5, 0.05)
    views = [render_two_planes(T, K) for T in poses]
    rng = np.random.default_rng(0)
    color, depth = views[2]
    noisy = depth * (1 + 0.01 * rng.standard_normal(depth.shape)).astype(np.float32)
    noisy[rng.random(depth.shape) < 0.1] = 0
    refs = [RefView(c, d, K, T) for i, ((c, d), T) in enumerate(zip(views, poses)) if i != 2]
    for backend in ("numba", "reference"):
        res = refine_depth(color, noisy.astype(np.float32), K, poses[2], refs,
                           RefineConfig(median_radius=2, backend=backend))
        out[f"refine/{backend}/depth"] = res.depth_m
        out[f"refine/{backend}/cost"] = res.cost


def fingerprint(work: Path | None, parts: tuple[str, ...] = ("sample", "apc", "refine")) -> dict[str, np.ndarray]:
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene
    from presim.capture.store import load_scene

    out: dict[str, np.ndarray] = {}
    if "refine" in parts:
        _refine(out)
    if "sample" not in parts:
        return out if "apc" not in parts else _apc(out)
    if work is None:
        sample_dir = common.sample_scene(frames=16, width=320, height=240, seed=0)
    else:
        sample_dir = work / "sample"
        if not sample_dir.is_dir():
            build_sample_scene(sample_dir, seed=0, config=SampleSceneConfig(width=320, height=240, num_frames=16))
    _render_scene("sample", load_scene(sample_dir), [(2, 3), (7, 8), (12, 13)], out)
    return out if "apc" not in parts else _apc(out)


def _apc(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if APC.is_dir():
        from presim.capture.importers import import_capture

        apc = import_capture(APC, align_floor=False)
        _render_scene("apc", apc, [(7, 8), (24, 25), (40, 41)], out)
        _reprojection(apc, "apc", out)
    else:
        print(f"{APC} missing: real-capture part skipped")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--save", type=Path, help="write the fingerprint into this folder")
    g.add_argument("--compare", type=Path, help="compare with the fingerprint saved in this folder")
    ap.add_argument("--work", type=Path, default=None,
                    help="where the sample scene is built once (default: the benchmarks' cache folder)")
    ap.add_argument("--parts", nargs="+", choices=("sample", "apc", "refine"), default=("sample", "apc", "refine"),
                    help="compute only these parts (--compare then checks only their arrays)")
    ap.add_argument("--forward-color", action="store_true",
                    help="render with backward_color=False: the algorithm of trees before backward colour sampling "
                         "(compare the kernels with such a tree)")
    ap.add_argument("--thesis-loop", action="store_true",
                    help="render with min_view_gain=0 (the thesis's adaptive loop), to compare kernels with a tree "
                         "whose default loop has no diminishing-returns stop")
    args = ap.parse_args(argv)
    common.setup()
    if args.thesis_loop:
        EXTRA["min_view_gain"] = 0.0
    if args.forward_color:
        EXTRA["backward_color"] = False
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
    fp = fingerprint(args.work, tuple(args.parts))
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.save / "fingerprint.npz", **{k.replace("/", "__"): v for k, v in fp.items()})
        print(f"saved {len(fp)} arrays to {args.save / 'fingerprint.npz'}")
        return 0
    ref = np.load(args.compare / "fingerprint.npz")
    ref = {k.replace("__", "/"): ref[k] for k in ref.files}
    ref = {k: v for k, v in ref.items() if k.split("/")[0] in args.parts}
    bad = 0
    for k in sorted(set(ref) | set(fp)):
        if k not in ref or k not in fp:
            print(f"MISSING {k}: {'before' if k not in ref else 'after'}")
            bad += 1
            continue
        a, b = ref[k], fp[k]
        if a.shape != b.shape or a.dtype != b.dtype:
            print(f"DIFF {k}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}")
            bad += 1
        elif a.tobytes() != b.tobytes():
            n = int(np.count_nonzero(a != b)) if a.ndim else 1
            print(f"DIFF {k}: {n} of {a.size} elements differ")
            bad += 1
    print(f"{len(fp)} arrays compared, {bad} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
