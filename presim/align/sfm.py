"""Initial poses for a capture that has none: incremental structure from motion (pycolmap), metric
scale from the depth.

``estimate_poses_sfm(scene, SfmConfig())``:

1. The scene's (already undistorted) color frames are written as lossless PNGs to a temporary folder
   with a COLMAP database beside them (never into the output scene); all frames share one PINHOLE
   camera with the scene's intrinsics, held fixed (no focal, principal point or distortion refinement).
2. SIFT extraction and matching in pycolmap: sequential pairs (each frame with the next
   ``sequential_overlap`` frames plus quadratic jumps 2, 4, 8...), and, for loop closure without a
   vocabulary tree (none can be downloaded here), each frame with its ``loop_neighbours`` most similar
   frames outside that window by a TF-IDF bag of words whose vocabulary is k-means on the capture's own
   descriptors (:func:`retrieval_pairs`). Exhaustive matching of 181 VGA frames was measured at about
   16 min on the shared 2-core machine, too slow. Two-view geometric verification by RANSAC.
3. COLMAP's incremental mapper with Ceres bundle adjustment. Initial-pair and triangulation angle
   thresholds are lowered because hand-held RGB-D captures are rotation-heavy (TUM fr1/rpy). If the
   mapper makes several models, the largest is kept and the others' frames are reported as not
   registered.
4. Metric scale: for every 3D point seen in a frame, the ratio of the sensor depth at the keypoint to
   the point's SfM depth in that frame; the scale is the median over all (frames are weighted equally
   by taking at most ``scale_samples_per_frame`` per frame), and the spread of the ratios (MAD / median)
   is reported. The world frame is the first registered frame's camera.

Deterministic for a seed: pycolmap's global seed, the RANSAC and mapper seeds are set, and the mapper
runs on one thread (Ceres sums in thread order otherwise). Extraction and matching run on
``num_threads`` (default 1: bit-identical poses are tested that way; more threads are faster but their
reproducibility is not tested).

Needs pycolmap 4.x (``pip install presim[sfm]``); :class:`SfmUnavailable` says so when it is missing.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from presim.align.bundle import BAConfig
from presim.align.features import appearance_similarity
from presim.align.pipeline import AlignConfig, align_poses
from presim.capture.scene import Scene
from presim.geometry import invert
from presim.io_utils import progress

__all__ = ["SfmConfig", "SfmError", "SfmResult", "SfmUnavailable", "estimate_poses", "estimate_poses_sfm",
           "metric_scale", "retrieval_pairs"]


class SfmError(ValueError):
    """SfM failed on this input (the message names the frames)."""


class SfmUnavailable(ImportError):
    """pycolmap is not installed."""


@dataclass(frozen=True)
class SfmConfig:
    max_features: int = 4096
    """SIFT keypoints per image (pycolmap's default is 8192; 4096 halves matching time on VGA frames)."""
    sequential_overlap: int = 10
    """Each frame is matched to this many following frames (plus quadratic jumps 2^k)."""
    loop_neighbours: int = 8
    """Loop closure: each frame is also matched to its this-many most similar frames outside the
    sequential window, by a bag-of-words built on the capture's own SIFT descriptors (no vocabulary
    tree to download). 0: sequential pairs only."""
    vocabulary_words: int = 256
    """Visual words of that bag-of-words (k-means on a seeded sample of the descriptors)."""
    init_min_tri_angle_deg: float = 4.0
    """Median triangulation angle the mapper's initial pair needs (COLMAP default 16 deg: too strict for
    rotation-heavy hand-held captures)."""
    min_tri_angle_deg: float = 1.0
    """Triangulation / filtering angle of the mapper's points (COLMAP default 1.5 deg)."""
    min_registered_frac: float = 0.8
    """Fewer registered frames than this fraction of the capture: :class:`SfmError` (nothing written)."""
    scale_samples_per_frame: int = 200
    """Depth ratios per frame used for the metric scale (seeded subset), so frames weigh alike."""
    num_threads: int = 1
    """Threads for feature extraction and matching (-1: all cores; 1: the tested deterministic setting).
    The mapper always runs on one thread (determinism)."""
    seed: int = 0
    """pycolmap's random seed (RANSAC, mapper) and the vocabulary's k-means seed."""
    quiet: bool = True
    """Hide COLMAP's per-image INFO log lines (warnings stay)."""


@dataclass(frozen=True)
class SfmResult:
    T_world_cam: np.ndarray
    """(N, 4, 4) metric camera-to-world poses of all frames; identity for frames not registered. The
    world is the first registered frame's camera."""
    registered_idxs: list[int]
    """Indices of the frames the mapper registered (in the largest model), increasing."""
    scale: float
    """Metres per SfM unit (median depth ratio)."""
    stats: dict
    """JSON-ready: models, pairs, scale spread, timings."""


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:
        raise SfmUnavailable("pose estimation for captures without poses needs pycolmap 4.x, which is not "
                             "installed: pip install 'presim[sfm]' (or 'pycolmap>=4,<5')") from e
    major = int(str(pycolmap.__version__).split(".")[0])
    if major != 4:
        raise SfmUnavailable(f"pose estimation needs pycolmap 4.x, found {pycolmap.__version__}: "
                             "pip install 'pycolmap>=4,<5'")
    return pycolmap


def metric_scale(sfm_depth: np.ndarray, sensor_depth_m: np.ndarray) -> tuple[float, float, int]:
    """(scale = median(sensor / sfm), spread = MAD / median of the ratios, count) over the pairs where
    both depths are valid (> 0). Raises :class:`SfmError` with fewer than 10 valid pairs."""
    ok = (sfm_depth > 0) & (sensor_depth_m > 0) & np.isfinite(sfm_depth) & np.isfinite(sensor_depth_m)
    r = sensor_depth_m[ok] / sfm_depth[ok]
    if len(r) < 10:
        raise SfmError(f"metric scale: only {len(r)} SfM points have sensor depth (need 10)")
    s = float(np.median(r))
    return s, float(np.median(np.abs(r - s)) / s), int(len(r))


def retrieval_pairs(descriptors: list[np.ndarray], config: SfmConfig) -> list[tuple[int, int]]:
    """Loop-closure pairs ``(a, b)``, a < b: for each frame its ``config.loop_neighbours`` most similar
    frames with ``|a - b| > config.sequential_overlap`` (those are matched sequentially), by cosine
    similarity of TF-IDF bag-of-words histograms (:func:`appearance_similarity`). The vocabulary is
    ``config.vocabulary_words`` k-means centres (10 Lloyd iterations, seeded) of at most 200
    descriptors per frame.

    ``descriptors``: one (M_i, 128) uint8 array per frame. Deterministic for ``config.seed``."""
    n, k = len(descriptors), config.loop_neighbours
    if k <= 0 or n <= config.sequential_overlap + 1:
        return []
    sim = appearance_similarity(descriptors, config.vocabulary_words, config.seed)
    if not sim.any():
        return []
    idx = np.arange(n)
    sim[np.abs(idx[:, None] - idx[None]) <= config.sequential_overlap] = -np.inf
    pairs = set()
    for a in range(n):
        for b in np.argsort(-sim[a], kind="stable")[:k]:
            if np.isfinite(sim[a, b]):
                pairs.add((min(a, int(b)), max(a, int(b))))
    return sorted(pairs)


def _depth_at(depth_m: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sensor depth at pixel centres ``uv`` (M, 2) (PreSim pixel convention); 0 outside or invalid."""
    h, w = depth_m.shape
    u = np.floor(uv[:, 0] + 0.5).astype(int)
    v = np.floor(uv[:, 1] + 0.5).astype(int)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(len(uv), np.float64)
    out[ok] = depth_m[v[ok], u[ok]]
    return out


def estimate_poses_sfm(scene: Scene, config: SfmConfig = SfmConfig(),
                       log: Callable[[str], None] | None = None) -> SfmResult:
    """Metric camera poses of ``scene`` by incremental SfM (see module doc).

    Raises :class:`SfmUnavailable` without pycolmap; :class:`SfmError` naming the frames when fewer than
    ``min_registered_frac`` of them register, or when the intrinsics differ between frames.
    """
    pycolmap = _pycolmap()
    log = log or (lambda s: None)
    n = len(scene)
    if n < 2:
        raise SfmError(f"SfM needs at least 2 frames, the capture has {n}")
    K = scene.intrinsics[0]
    if any(k != K for k in scene.intrinsics[1:]):
        raise SfmError("SfM needs one camera: the frames' intrinsics differ")
    t0 = time.perf_counter()
    pycolmap.set_random_seed(config.seed)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1 if config.quiet else 0  # COLMAP's per-image INFO lines otherwise
    try:
        models, names, n_pairs, loops, times = _run_colmap(pycolmap, scene, config, log)
    finally:
        pycolmap.logging.minloglevel = level
    cam_from_world = {}
    sizes: list[tuple[int, int]] = []
    if models:
        sizes = sorted(((m.num_reg_images(), k) for k, m in models.items()), reverse=True)
        rec = models[sizes[0][1]]
        name_to_idx = {nm: i for i, nm in enumerate(names)}
        for img in rec.images.values():
            if img.has_pose:
                cam_from_world[name_to_idx[img.name]] = img
    reg = sorted(cam_from_world)
    lost = [i for i in range(n) if i not in cam_from_world]
    if len(reg) < config.min_registered_frac * n:
        why = "" if models else " (the mapper found no initial pair: too little texture, overlap or parallax?)"
        raise SfmError(f"only {len(reg)} of {n} frames could be registered by SfM (need "
                       f"{config.min_registered_frac:.0%}); not registered: {_names(scene, lost)}{why}")

    # metric scale from the sensor depth at the keypoints
    rng = np.random.default_rng(config.seed)
    sfm_z, sensor_z = [], []
    for i in reg:
        img = cam_from_world[i]
        pts = [(p.xy, p.point3D_id) for p in img.points2D if p.has_point3D()]
        if not pts:
            continue
        if len(pts) > config.scale_samples_per_frame:
            pts = [pts[j] for j in np.sort(rng.choice(len(pts), config.scale_samples_per_frame, replace=False))]
        xy = np.array([p[0] for p in pts], np.float64) - 0.5
        X = np.array([rec.points3D[p[1]].xyz for p in pts], np.float64)
        M = img.cam_from_world().matrix()
        sfm_z.append(X @ M[:3, :3][2] + M[2, 3])
        sensor_z.append(_depth_at(scene.frames.load(i)[1], xy))
    try:
        scale, spread, count = metric_scale(np.concatenate(sfm_z), np.concatenate(sensor_z))
    except (SfmError, ValueError) as e:
        raise SfmError(f"SfM poses found but {e}") from None

    T = np.tile(np.eye(4), (n, 1, 1))
    for i in reg:
        M = np.eye(4)
        M[:3] = cam_from_world[i].cam_from_world().matrix()
        M[:3, 3] *= scale
        T[i] = invert(M)
    T_first = invert(T[reg[0]])
    for i in reg:
        T[i] = T_first @ T[i]
    stats = {
        "frames": n, "registered": len(reg), "not_registered": [scene.frame_ids[i] for i in lost],
        "models": [s for s, _ in sizes], "loop_pairs": len(loops),
        "matched_pairs": n_pairs, "points3d": int(rec.num_points3D()),
        "mean_reprojection_px": float(rec.compute_mean_reprojection_error()),
        "scale_m_per_unit": scale, "scale_spread_mad_rel": spread, "scale_samples": count,
        "time_s": {"features": times[0], "matching": times[1], "mapping": times[2],
                   "total": time.perf_counter() - t0},
        "config": asdict(config),
    }
    if len(models) > 1:
        log(f"sfm: the mapper made {len(models)} models (frames {[s for s, _ in sizes]}); kept the largest")
    log(f"sfm: registered {len(reg)} of {n} frames, {stats['points3d']} points, reprojection "
        f"{stats['mean_reprojection_px']:.2f} px, scale {scale:.4f} m/unit (spread {spread:.1%} MAD over "
        f"{count} keypoints), {stats['time_s']['total']:.0f} s")
    return SfmResult(T, reg, scale, stats)


def _run_colmap(pycolmap, scene: Scene, config: SfmConfig, log: Callable[[str], None]):
    """Images + database in a temporary folder, features, matching, mapping: (models, image names,
    verified pairs, loop pairs, (t_features, t_matching, t_mapping))."""
    n, K = len(scene), scene.intrinsics[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="presim-sfm-") as tmp:
        tmp = Path(tmp)
        img_dir, db_path, out_dir = tmp / "images", tmp / "database.db", tmp / "sparse"
        img_dir.mkdir()
        out_dir.mkdir()
        names = [f"{i:06d}.png" for i in range(n)]
        for i in progress(range(n), desc="sfm: write frames", unit="frame"):
            # fast lossless PNG (temporary files: no atomic write needed)
            cv2.imwrite(str(img_dir / names[i]), cv2.cvtColor(scene.frames.load(i)[0], cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_PNG_COMPRESSION, 1])
        # COLMAP puts pixel centres at +0.5 (its origin is the top-left corner); PreSim at integers.
        reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE",
                                             camera_params=f"{K.fx},{K.fy},{K.cx + 0.5},{K.cy + 0.5}")
        ext = pycolmap.FeatureExtractionOptions(num_threads=config.num_threads)
        ext.sift.max_num_features = config.max_features
        pycolmap.extract_features(db_path, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        t_ext = time.perf_counter()
        match = pycolmap.FeatureMatchingOptions(num_threads=config.num_threads)
        verify = pycolmap.TwoViewGeometryOptions()
        verify.ransac.random_seed = config.seed
        seq = pycolmap.SequentialPairingOptions(overlap=config.sequential_overlap, quadratic_overlap=True)
        pycolmap.match_sequential(db_path, matching_options=match, pairing_options=seq,
                                  verification_options=verify, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(db_path)
        ids = {img.name: img.image_id for img in db.read_all_images()}
        desc = [np.asarray(db.read_descriptors(ids[nm]).data) for nm in names]
        db.close()
        loops = retrieval_pairs(desc, config)
        if loops:
            pairs_path = tmp / "loop_pairs.txt"
            pairs_path.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in loops))
            pycolmap.match_image_pairs(db_path, matching_options=match,
                                       pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
                                       verification_options=verify, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(db_path)
        n_pairs = int(db.num_verified_image_pairs())
        db.close()
        t_match = time.perf_counter()
        log(f"sfm: {n} frames, features {t_ext - t0:.0f} s, matching {t_match - t_ext:.0f} s "
            f"({len(loops)} loop pairs), {n_pairs} pairs with two-view geometry")
        opts = _mapper_options(pycolmap, config)
        # progress: one tick per image the mapper registers (the initial pair counts two)
        with progress(total=n, desc="sfm: mapping", unit="frame") as bar:
            models = pycolmap.incremental_mapping(db_path, img_dir, out_dir, options=opts,
                                                  initial_image_pair_callback=lambda: bar.update(2),
                                                  next_image_callback=lambda: bar.update(1))
        t_map = time.perf_counter()
    return models, names, n_pairs, loops, (t_ext - t0, t_match - t_ext, t_map - t_match)


def _mapper_options(pycolmap, config: SfmConfig):
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    opts.random_seed = config.seed
    opts.multiple_models = True
    opts.extract_colors = False
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    m = opts.mapper
    m.num_threads = 1
    m.random_seed = config.seed
    m.abs_pose_refine_focal_length = False
    m.abs_pose_refine_extra_params = False
    m.init_min_tri_angle = config.init_min_tri_angle_deg
    m.filter_min_tri_angle = config.min_tri_angle_deg
    opts.triangulation.min_angle = config.min_tri_angle_deg
    opts.triangulation.random_seed = config.seed
    return opts


def _names(scene: Scene, idxs: list[int], limit: int = 8) -> str:
    s = ", ".join(scene.frame_ids[i] for i in idxs[:limit])
    return s + (f" and {len(idxs) - limit} more" if len(idxs) > limit else "")


def estimate_poses(scene: Scene, config: SfmConfig = SfmConfig()) -> Scene:
    """Poses for a capture without poses (the ``estimate_poses`` argument of
    :func:`presim.capture.importers.import_capture`): incremental SfM (pycolmap) with metric scale
    from the depth, then the local-to-global alignment (docs/alignment.md). Unregistered frames are
    dropped and named in ``scene.meta.notes`` and on stderr.

    Example:
        >>> from functools import partial
        >>> est = partial(estimate_poses, config=SfmConfig(seed=1))
        >>> scene = import_capture("capture/", estimate_poses=est)     # doctest: +SKIP
    """
    def log(s: str) -> None:
        print(s, file=sys.stderr)

    res = estimate_poses_sfm(scene, config, log=log)
    reg = res.registered_idxs
    lost = [scene.frame_ids[i] for i in range(len(scene)) if i not in set(reg)]
    sub = replace(scene.subset(reg), T_world_cam=res.T_world_cam[reg], poses_source="given")
    # depth residuals on and no appearance pairs / second pass (no auto rule): the configuration the
    # pose-less import was measured with (docs/alignment.md)
    aligned = align_poses(sub, AlignConfig(keep_unmatched=True, ba=BAConfig(use_depth=True), appearance_neighbours=0,
                                           rematch_rounds=0), log=log)
    st = res.stats
    notes = [f"poses estimated from the images (pycolmap incremental SfM, metric scale "
             f"{st['scale_m_per_unit']:.4g} m/unit from the depth, spread {st['scale_spread_mad_rel']:.1%} MAD; "
             f"then local-to-global alignment); {len(reg)} of {len(scene)} frames registered"]
    if len(st["models"]) > 1:
        notes.append(f"SfM made {len(st['models'])} models ({st['models']} frames): the largest was kept")
    if lost:
        notes.append(f"not registered (left out): {', '.join(lost)}")
        print(f"import: {len(lost)} frame(s) could not be registered and were left out: {', '.join(lost[:10])}"
              + (f" and {len(lost) - 10} more" if len(lost) > 10 else ""), file=sys.stderr)
    return replace(sub, T_world_cam=aligned.T_world_cam,
                   meta=replace(sub.meta, notes=sub.meta.notes + tuple(notes)))
