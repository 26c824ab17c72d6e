"""``presim photometric``: per-frame colour calibration of a saved scene (exposure / white balance)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    from presim.capture.calibration import PHOTOMETRIC_MODELS

    p = sub.add_parser("photometric", help="calibrate per-frame exposure/white balance of a scene (photometric.json)",
                       description="Solves one colour transform per frame jointly over overlapping frames "
                                   "(correspondences by depth reprojection), anchored at the capture's mean "
                                   "exposure, and writes SCENE/photometric.json; the images are never changed. "
                                   "The renderer applies it (RenderConfig.use_photometric, exposure_frame).")
    p.add_argument("scene", type=Path, help="saved scene folder")
    p.add_argument("--model", choices=PHOTOMETRIC_MODELS, default="gain_bias",
                   help="gain_bias: per-channel gain and bias; gain: per-channel gain only; "
                        "affine: 3x3 colour matrix and bias")
    p.add_argument("--vignetting", action="store_true",
                   help="also solve one radial vignetting term shared by all frames")
    p.add_argument("--neighbors", type=int, default=6, help="frames paired with each frame (default 6)")
    p.add_argument("--raw-depth", action="store_true", help="use the raw depth even when refined depth exists")
    p.add_argument("--overwrite", action="store_true", help="replace an existing photometric.json")
    p.set_defaults(func=_cmd_photometric)


def _cmd_photometric(args: argparse.Namespace) -> int:
    import numpy as np

    from presim.photometric import PhotometricConfig, calibrate_photometric
    from presim.capture.store import PHOTOMETRIC_FILE, load_scene, save_photometric

    if args.neighbors < 1:
        raise ValueError(f"--neighbors must be >= 1, got {args.neighbors}")
    scene = load_scene(args.scene)
    if (args.scene / PHOTOMETRIC_FILE).exists() and not args.overwrite:
        raise FileExistsError(f"{args.scene / PHOTOMETRIC_FILE}: already exists (pass --overwrite to replace it)")
    cfg = PhotometricConfig(model=args.model, vignetting=args.vignetting, num_neighbors=args.neighbors,
                            use_refined_depth=not args.raw_depth)
    calib = calibrate_photometric(scene, cfg)
    out = save_photometric(args.scene, calib)
    st = calib.stats
    g = calib.gain.mean(axis=1)
    print(f"wrote {out}: {len(calib.frame_ids)} frames, {st['pairs']} pairs, {st['samples']} samples, "
          f"{st['seconds']:.1f} s")
    print(f"gain (mean of RGB) min {g.min():.3f} median {np.median(g):.3f} max {g.max():.3f}; "
          f"residual RMS {np.mean(st['rms_before']):.2f} -> {np.mean(st['rms_after']):.2f} levels"
          + (f"; {st['frames_without_samples']} frames without correspondences (identity)"
             if st["frames_without_samples"] else ""))
    if calib.vignetting is not None:
        k1, k2 = calib.vignetting
        print(f"vignetting: k1 {k1:.4f} k2 {k2:.4f} (fall-off at the image corner {1 / (1 + k1 + k2):.3f})")
    return 0
