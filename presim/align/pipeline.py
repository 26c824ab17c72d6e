"""``align_poses``: local-to-global RGB-D bundle adjustment of a scene's camera poses (thesis §5.3.3).

1. SIFT features of every frame, with the (raw) depth at each keypoint.
2. Groups of <= 10 poses around seeded random key poses (:func:`group_poses`).
3. Local: the key image's features matched to each group member (ratio test + PnP RANSAC); 3D points
   from the key's depth (thesis eq. 5.1: fixed reference points lifted with the key's pose); adjustment
   of the members' poses (:func:`adjust_poses`: reprojection + depth residuals, Huber), key fixed.
4. Global: key images matched to their nearest keys using only features the local stage kept;
   adjustment of the key poses (first key fixed); members follow their key rigidly.
5. Joint (beyond the thesis, ``joint=True``): each frame also matched to its nearest frames (and,
   with ``appearance_neighbours``, to its most similar frames in appearance: pose-free), then one
   adjustment of all frames with all observations, started from step 4. Optional second matching
   pass (``rematch_rounds``): frames left unconnected or weakly connected are matched again at their
   neighbours' refined poses with the gate grown to their pose uncertainty (``predicted_match_cov``),
   and all frames are adjusted again. Both default to ``auto``: after a first pass without them,
   :func:`pose_noise_evidence` compares the relative camera-centre corrections between verified
   pairs with the spacing of the centres; when the given poses are too noisy for neighbours chosen
   by distance, steps 4-5b are done again with them (pairs already matched are reused).
6. The refined trajectory is moved rigidly onto the given one (rotation: chordal mean, translation:
   mean of centre offsets), so floor, objects and point cloud keep their world frame.
7. Acceptance (``accept_t > 0``): per frame, a paired test of its observations' costs under the given
   vs the refined poses; a frame whose refined pose does not lower them significantly (or that has too
   few observations) keeps its given pose, and the other frames are adjusted again with those held
   fixed (they anchor the gauge: no frame drifts relative to a neighbour left at its given pose).
   Per-frame status, test statistic and pose uncertainty go into the statistics.
Deterministic for a seed (OpenCV RANSAC is seeded per pair; scipy's solver is deterministic).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from presim.align.bundle import (BAConfig, PairObservations, adjust_poses, observation_costs,
                                         pose_covariances, pose_information, residuals_px)
from presim.align.features import (FeatureConfig, Features, PairMatch, appearance_similarity, extract_features,
                                           match_pair, unproject_uv)
from presim.align.grouping import GroupConfig, group_poses, view_angles_rad
from presim.capture.scene import Scene
from presim.geometry import invert as invert_pose
from presim.io_utils import progress

__all__ = ["AlignConfig", "AlignError", "AlignResult", "align_poses", "fit_rigid_to", "pose_change",
           "pose_noise_evidence"]


class AlignError(ValueError):
    """Alignment impossible with this input (the message names the frames)."""


@dataclass(frozen=True)
class AlignConfig:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    grouping: GroupConfig = field(default_factory=GroupConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    global_neighbours: int = 4
    """Each key image is matched to this many nearest keys (within the FOV) for the global stage."""
    joint: bool = True
    """Finish with one bundle adjustment of all frames (beyond the thesis; ablation: False)."""
    joint_neighbours: int = 6
    """For the joint pass, each frame is also matched to this many nearest frames (camera-centre
    distance, viewing directions within the FOV): links neighbouring groups, whose members the
    thesis' stages never match to each other."""
    appearance_neighbours: int | None = None
    """For the joint pass, each frame is also matched to this many frames most similar in appearance
    (TF-IDF bag of SIFT words, :func:`appearance_similarity`) among those within the FOV, and the
    second pass's weak frames to as many: neighbours chosen by camera-centre distance inherit the
    poses' errors (measured on TUM fr1/rpy, whose camera centres move 1.2 cm per frame: with 3 cm pose
    noise the nearest centres are unrelated frames and 11 frames found no match), the images'
    similarity does not. The long-range pairs cost ~0.1 dB when the given poses are good
    (docs/alignment.md). None = auto (default): 0, unless the first pass measures poses too noisy for
    distance-based neighbours (:func:`pose_noise_evidence`, ``auto_noise_ratio``); then the matching
    is done again with ``auto_appearance_neighbours``. 0 = pose-based neighbours only."""
    rematch_rounds: int | None = None
    """Second matching pass (needs ``joint``): frames that the first pass left outside the connected
    set, or with fewer than ``min_frame_obs`` verified matches, are matched again against their
    neighbours (pose and appearance) at the neighbours' refined poses, with the gate grown to the
    uncertainty of the frame's given pose (:func:`predicted_match_cov`, ``pose_sigma_deg`` /
    ``pose_sigma_m``); frames that join start at their PnP pose and all frames are adjusted again.
    Repeated while frames join, at most this many rounds. None = auto (default): 0, or
    ``auto_rematch_rounds`` when the auto rule fires. 0 = one pass only (measured neutral on TUM from
    mocap alone, and worse alone from the perturbed start, 2.02 cm vs 1.88; with appearance neighbours
    part of the 0.82 cm run)."""
    auto_noise_ratio: float = 0.25
    """Auto rule (either of the two above None): after the first pass, the matching is done again with
    the appearance neighbours and the second pass when the relative camera-centre noise of the given
    poses (what the first pass corrected between verified pairs) exceeds this fraction of the spacing
    of the camera centres (distance to the ``joint_neighbours``-th nearest): see
    :func:`pose_noise_evidence` and docs/alignment.md for why 0.25 and the measured values."""
    auto_appearance_neighbours: int = 6
    """``appearance_neighbours`` when the auto rule fires."""
    auto_rematch_rounds: int = 3
    """``rematch_rounds`` when the auto rule fires."""
    rematch_neighbours: int = 6
    """Second pass: each weak frame is tried with this many nearest connected frames (current poses,
    within the FOV), besides its ``appearance_neighbours`` most similar ones."""
    pose_sigma_deg: float | None = None
    """Stated noise of the given poses (1 sigma per axis, degrees; with ``pose_sigma_m``): every
    matching gate is then the predicted-match covariance gate of both frames' noise instead of the
    fixed ``features.prior_px``. None = first pass with the fixed gate, second pass with the noise
    measured by the first: the RMS per axis of the changes it made to the connected frames."""
    pose_sigma_m: float | None = None
    """As ``pose_sigma_deg`` for the camera centres (metres)."""
    max_matches_per_pair: int = 200
    """Verified matches per image pair used by the adjustments (seeded random subset): bounds the time."""
    min_features: int = 20
    """A frame with fewer SIFT keypoints with depth is an error (named)."""
    keep_unmatched: bool = False
    """Frames no verified match connects to the rest (or with too few features): False = error naming
    them; True = keep their given pose."""
    seed: int = 0
    """Key-pose draw and RANSAC seeds."""
    accept_t: float = 3.0
    """Per-frame acceptance: a frame takes its refined pose only when the refined poses lower the
    reprojection cost of its observations measurably: the paired t statistic
    ``mean(d) / (std(d) / sqrt(n_obs))`` above this, d = an observation's Huber reprojection cost under
    the given poses minus the one under the refined poses, over the frame's inlier observations (the
    improvement must exceed ``accept_t`` standard errors of the measured noise). The depth residuals
    are left out of the test on purpose: a sensor's depth errors are systematic per frame (a depth
    map registered pixels off its colour image, depth-dependent bias), a pose that absorbs them lowers
    the depth cost of every observation of the frame, while the reprojection of a feature lifted with
    a wrong depth moves only by parallax (docs/alignment.md has the measurements). Measured t: exact
    poses 0-6, real pose errors 4-37. At least half of the frame's image pairs must also pass the same
    test on their own observations: a wrong neighbour improves only the pairs it is in, so an exact
    frame next to it keeps its given pose. 0 = accept all refined poses (no test)."""
    accept_chi2: float = 16.81
    """... and only when its own pose change is measurable: ``delta^T I delta`` above this, with
    ``delta`` the 6-vector change (rotation vector, translation) from the given pose and ``I`` the
    frame's own information (all other frames held; residual noise level measured from the data).
    16.81 = the 99 % quantile of chi-square with 6 degrees of freedom: a change inside the frame's
    own 99 % confidence region is not measurable and the given pose is kept."""
    min_frame_obs: int = 30
    """A frame with fewer inlier observations than this keeps its given pose (too weakly connected to
    test or to trust)."""
    accept_rounds: int = 5
    """Test, re-adjust the others with the kept frames fixed, test again, until no frame changes
    side: at most this many re-adjustments (then the last test only moves frames to their given pose)."""


@dataclass(frozen=True)
class AlignResult:
    T_world_cam: np.ndarray
    """(N, 4, 4) refined camera-to-world poses, in the scene's world frame."""
    stats: dict
    """JSON-ready: groups, pairs, matches, transfer errors before/after, per-frame change, timings."""


Pair = tuple[int, int, PairMatch]


def pose_change(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame (translation m, rotation deg) between two (N, 4, 4) pose sets."""
    dt = np.linalg.norm(T_a[:, :3, 3] - T_b[:, :3, 3], axis=1)
    Rrel = np.einsum("nji,njk->nik", T_a[:, :3, :3], T_b[:, :3, :3])
    c = np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return dt, np.degrees(np.arccos(c))


def fit_rigid_to(T_ref: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """4x4 ``S`` minimising sum ||S @ T_est_i - T_ref_i|| over rotations (chordal mean of
    ``R_ref R_est^T``) and camera centres (mean offset after rotation)."""
    M = np.einsum("nij,nkj->ik", T_ref[:, :3, :3], T_est[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    t = np.mean(T_ref[:, :3, 3] - T_est[:, :3, 3] @ R.T, axis=0)
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, t
    return S


def _K4(scene: Scene, i: int) -> np.ndarray:
    K = scene.intrinsics[i]
    return np.array([K.fx, K.fy, K.cx, K.cy])


def _pair_obs(pairs: list[Pair], feats: list[Features], scene: Scene, cams: list[int],
              max_per_pair: int, seed: int) -> tuple[PairObservations, np.ndarray, dict[int, int]]:
    """Observations of ``pairs`` over the frames ``cams`` (local indices), at most ``max_per_pair``
    matches per pair (a seeded random subset); also each observation's feature index in a."""
    slot = {c: k for k, c in enumerate(cams)}
    rng = np.random.default_rng(seed)
    A, B, X, UV, Z, FA = [], [], [], [], [], []
    for a, b, m in pairs:
        sel = np.arange(len(m.idx_a))
        if len(sel) > max_per_pair:
            sel = np.sort(rng.choice(len(sel), max_per_pair, replace=False))
        ia, ib = m.idx_a[sel], m.idx_b[sel]
        fa, fb = feats[a], feats[b]
        X.append(unproject_uv(scene.intrinsics[a], fa.uv[ia].astype(np.float64), fa.depth_m[ia].astype(np.float64)))
        A.append(np.full(len(ia), slot[a]))
        B.append(np.full(len(ia), slot[b]))
        UV.append(fb.uv[ib].astype(np.float64))
        Z.append(fb.depth_m[ib].astype(np.float64))
        FA.append(ia)
    obs = PairObservations(np.concatenate(A), np.concatenate(B), np.concatenate(X), np.concatenate(UV),
                           np.concatenate(Z))
    return obs, np.concatenate(FA), slot


def _K4s(scene: Scene, cams: list[int]) -> np.ndarray:
    return np.stack([_K4(scene, c) for c in cams])


def transfer_errors(pairs: list[Pair], feats: list[Features], scene: Scene,
                    T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Feature transfer errors of all verified matches under poses ``T_world_cam``: each keypoint of a
    is lifted with a's depth, moved to b, projected: (pixel error (M,), |depth residual| m, NaN without
    b depth). The pose-only measure reported before/after alignment."""
    errs, dres = [], []
    for a, b, m in pairs:
        Xa = unproject_uv(scene.intrinsics[a], feats[a].uv[m.idx_a].astype(np.float64),
                          feats[a].depth_m[m.idx_a].astype(np.float64))
        T_ba = invert_pose(T_world_cam[b]) @ T_world_cam[a]
        Xw = Xa  # points in a's frame; camera b seen from a
        n = len(Xa)
        e, d = residuals_px(T_ba[None], _K4(scene, b)[None], Xw, np.zeros(n, int), np.arange(n),
                            feats[b].uv[m.idx_b].astype(np.float64), feats[b].depth_m[m.idx_b].astype(np.float64))
        errs.append(e)
        dres.append(d)
    if not errs:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(errs), np.concatenate(dres)


def _components(n: int, edges: list[tuple[int, int]]) -> list[list[int]]:
    parent = list(range(n))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in edges:
        parent[find(a)] = find(b)
    comps: dict[int, list[int]] = {}
    for i in range(n):
        comps.setdefault(find(i), []).append(i)
    return sorted(comps.values(), key=lambda c: (-len(c), c[0]))


def _names(scene: Scene, idxs: list[int], limit: int = 8) -> str:
    s = ", ".join(scene.frame_ids[i] for i in idxs[:limit])
    return s + (f" and {len(idxs) - limit} more" if len(idxs) > limit else "")


def _stat(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return {"median": None, "mean": None, "p90": None}
    return {"median": float(np.median(x)), "mean": float(np.mean(x)), "p90": float(np.percentile(x, 90))}


def align_poses(scene: Scene, config: AlignConfig = AlignConfig(),
                log: Callable[[str], None] | None = None) -> AlignResult:
    """Refined camera poses of ``scene`` (see module doc). Raises :class:`AlignError` naming the frames
    when a frame has no depth or too few features, or the frames do not form one connected set."""
    t_start = time.perf_counter()
    log = log or (lambda s: None)
    n = len(scene)
    if n < 2:
        raise AlignError(f"alignment needs at least 2 frames, the scene has {n}")
    T_given = np.asarray(scene.T_world_cam, dtype=np.float64).copy()
    fc = config.features

    # 1. features
    feats: list[Features] = []
    no_depth, few = [], []
    for i in progress(range(n), desc="align: features", unit="frame"):
        color, depth = scene.frames.load(i)
        if not np.any(depth > 0):
            no_depth.append(i)
        f = extract_features(color, depth, fc)
        if int(np.count_nonzero(f.depth_m > 0)) < config.min_features:
            few.append(i)
        feats.append(f)
    if no_depth:
        raise AlignError(f"{len(no_depth)} frame(s) with no valid depth: {_names(scene, no_depth)}")
    if few and not config.keep_unmatched:
        raise AlignError(f"{len(few)} frame(s) with fewer than {config.min_features} SIFT features with depth "
                         f"(texture-less or blurred?): {_names(scene, few)} (--keep-unmatched keeps their given poses)")
    t_feat = time.perf_counter()

    # 2. groups
    fov = float(np.radians(scene.intrinsics[0].hfov_deg))
    groups = group_poses(T_given, fov, config.grouping, seed=config.seed)
    pair_seed = config.seed * 1_000_003

    # stated noise of the given poses: every prior gate grows to it (else the fixed prior_px)
    sig0 = None
    if config.pose_sigma_deg is not None and config.pose_sigma_m is not None:
        r0 = float(np.radians(config.pose_sigma_deg))
        sig0 = (r0, config.pose_sigma_m, r0, config.pose_sigma_m)

    # 3. local
    T_local = T_given.copy()
    local_pairs: list[Pair] = []
    used: dict[int, set[int]] = {}
    for g in progress(groups, desc="align: local groups", unit="group"):
        pairs = []
        for m in g.member_idxs:
            pm = match_pair(feats[g.key_idx], feats[m], scene.intrinsics[g.key_idx], scene.intrinsics[m], fc,
                            seed=pair_seed + g.key_idx * n + m, T_b_a_prior=_rel(T_given, g.key_idx, m),
                            prior_sigma=sig0)
            if pm is not None:
                pairs.append((g.key_idx, m, pm))
        if not pairs:
            continue
        cams = [g.key_idx] + [b for _, b, _ in pairs]
        obs, feat_a, slot = _pair_obs(pairs, feats, scene, cams, config.max_matches_per_pair, config.seed + g.key_idx)
        res = adjust_poses(T_given[cams], np.arange(len(cams)) == 0, _K4s(scene, cams), obs, config.ba)
        for c in cams[1:]:
            T_local[c] = res.T_world_cam[slot[c]]
        used[g.key_idx] = set(feat_a[res.inlier].tolist())
        local_pairs.extend(pairs)

    # 4. global over key poses
    keys = [g.key_idx for g in groups]
    key_centres = T_given[keys, :3, 3]
    global_pairs: list[Pair] = []
    done = set()
    for ka in progress(keys, desc="align: key matches", unit="key"):
        ang = view_angles_rad(T_given[keys], keys.index(ka))
        dist = np.linalg.norm(key_centres - T_given[ka, :3, 3], axis=1)
        order = [keys[j] for j in np.argsort(dist, kind="stable") if keys[j] != ka and ang[j] <= fov]
        for kb in order[: config.global_neighbours]:
            if (min(ka, kb), max(ka, kb)) in done:
                continue
            done.add((min(ka, kb), max(ka, kb)))
            fa, fb = _restrict(feats[ka], used.get(ka), fc), _restrict(feats[kb], used.get(kb), fc)
            pm = match_pair(fa[0], fb[0], scene.intrinsics[ka], scene.intrinsics[kb], fc, seed=pair_seed + ka * n + kb,
                            T_b_a_prior=_rel(T_local, ka, kb), prior_sigma=sig0)
            if pm is not None:
                global_pairs.append((ka, kb, PairMatch(fa[1][pm.idx_a], fb[1][pm.idx_b], pm.T_b_a)))

    # neighbour pairs for the joint pass (beyond the thesis); pairs are matched once (cache) even when
    # the matching is redone with the appearance pairs (auto rule below)
    cache: dict[tuple[int, int], PairMatch | None] = {}
    sim_box: list[np.ndarray] = []

    def similarity() -> np.ndarray:
        if not sim_box:
            s = appearance_similarity([f.desc for f in feats], seed=config.seed)
            np.fill_diagonal(s, -np.inf)
            sim_box.append(s)
        return sim_box[0]

    def neighbour_matches(k_app: int) -> list[Pair]:
        pairs: list[Pair] = []
        if not config.joint or (config.joint_neighbours <= 0 and k_app <= 0):
            return pairs
        have = {(min(a, b), max(a, b)) for a, b, _ in local_pairs + global_pairs}
        centres = T_given[:, :3, 3]
        sim = similarity() if k_app > 0 else None
        for i in progress(range(n), desc="align: neighbour matches", unit="frame"):
            ang = view_angles_rad(T_given, i)
            dist = np.linalg.norm(centres - centres[i], axis=1)
            order = [int(j) for j in np.argsort(dist, kind="stable") if j != i and ang[j] <= fov]
            order = order[: config.joint_neighbours]
            if sim is not None:  # pose-free candidates: the images' own similarity
                order += [int(j) for j in np.argsort(-sim[i], kind="stable") if ang[j] <= fov][:k_app]
            for j in order:
                key = (min(i, j), max(i, j))
                if key in have:
                    continue
                have.add(key)
                if (i, j) not in cache:
                    cache[(i, j)] = match_pair(feats[i], feats[j], scene.intrinsics[i], scene.intrinsics[j], fc,
                                               seed=pair_seed + i * n + j, T_b_a_prior=_rel(T_given, i, j),
                                               prior_sigma=sig0)
                if cache[(i, j)] is not None:
                    pairs.append((i, j, cache[(i, j)]))
        return pairs

    def matching_pass(k_app: int, rounds: int) -> dict:
        """Steps 4 (key adjustment) to 5b with ``k_app`` appearance neighbours and ``rounds`` second
        passes: pairs, connected set, poses (rigidly fitted onto the given ones) before acceptance."""
        neighbour_pairs = neighbour_matches(k_app)
        all_pairs = local_pairs + global_pairs + neighbour_pairs
        comps = _components(n, [(a, b) for a, b, _ in all_pairs])
        main = set(comps[0])
        T_glob = T_local.copy()
        if global_pairs:
            gkeys = sorted({k for a, b, _ in global_pairs for k in (a, b)} & main)
            gpairs = [p for p in global_pairs if p[0] in main]
            obs, _, slot = _pair_obs(gpairs, feats, scene, gkeys, config.max_matches_per_pair, config.seed + 1)
            res = adjust_poses(T_local[gkeys], np.arange(len(gkeys)) == 0, _K4s(scene, gkeys), obs, config.ba)
            member_of = {m: g.key_idx for g in groups for m in g.member_idxs}
            for k in gkeys:
                T_glob[k] = res.T_world_cam[slot[k]]
            for m, k in member_of.items():
                if k in slot:
                    T_glob[m] = T_glob[k] @ invert_pose(T_local[k]) @ T_local[m]

        # 5. joint
        def joint(T_start: np.ndarray) -> np.ndarray:
            cams = sorted(main)
            jpairs = [p for p in all_pairs if p[0] in main and p[1] in main]
            gauge = keys[0] if keys[0] in main else cams[0]
            obs, _, slot = _pair_obs(jpairs, feats, scene, cams, config.max_matches_per_pair, config.seed + 2)
            res = adjust_poses(T_start[cams], np.array([c == gauge for c in cams]), _K4s(scene, cams), obs,
                               config.ba)
            T = T_start.copy()
            for c in cams:
                T[c] = res.T_world_cam[slot[c]]
            return T

        def fit(T_ref: np.ndarray) -> np.ndarray:
            """6. rigid fit onto the given trajectory (frames in the main component)"""
            idx = sorted(main)
            T = T_given.copy()
            T[idx] = fit_rigid_to(T_given[idx], T_ref[idx]) @ T_ref[idx]
            return T

        T_out = fit(joint(T_glob) if config.joint and all_pairs else T_glob)
        first = {"T_out": T_out, "pairs": list(all_pairs), "main": set(main)}

        # 5b. second matching pass: weakly or not connected frames, gate grown to their pose uncertainty
        rematched: list[int] = []
        pose_sigma: tuple[float, float] | None = None
        for _ in range(rounds if config.joint and all_pairs else 0):
            weak = _weak_frames(n, all_pairs, main, config.min_frame_obs)
            if not weak:
                break
            if pose_sigma is None:
                pose_sigma = _given_pose_sigma(T_given, T_out, sorted(main), config)
            new_pairs, joined = _rematch(weak, main, all_pairs, feats, scene, T_out, pose_sigma,
                                         similarity() if k_app > 0 else None, k_app, fov, config, pair_seed)
            if not new_pairs:
                break
            neighbour_pairs.extend(new_pairs)
            all_pairs = local_pairs + global_pairs + neighbour_pairs
            comps = _components(n, [(a, b) for a, b, _ in all_pairs])
            main = set(comps[0])
            rematched.extend(sorted({i for p in new_pairs for i in p[:2] if i in weak}))
            # start the joined frames at their PnP pose (in the world frame of T_out), then adjust all again
            T_start = T_out.copy()
            for u, T_u in joined.items():
                T_start[u] = T_u
            T_out = fit(joint(T_start))
        unmatched = sorted(i for c in comps[1:] for i in c)
        return {"neighbour_pairs": neighbour_pairs, "all_pairs": all_pairs, "main": main, "unmatched": unmatched,
                "T_out": T_out, "rematched": rematched, "pose_sigma": pose_sigma, "first": first}

    t_stages = time.perf_counter()
    k_app = config.appearance_neighbours if config.appearance_neighbours is not None else 0
    rounds = config.rematch_rounds if config.rematch_rounds is not None else 0
    P = matching_pass(k_app, rounds)
    # auto rule: are the given poses too noisy for neighbours chosen by camera-centre distance?
    auto = config.appearance_neighbours is None or config.rematch_rounds is None
    evidence = None
    if auto and config.joint:
        f1 = P["first"]
        evidence = pose_noise_evidence(T_given, f1["T_out"], [(a, b) for a, b, _ in f1["pairs"]], f1["main"],
                                       max(1, config.joint_neighbours), fov, config.auto_noise_ratio)
        evidence["weak_frames"] = len(_weak_frames(n, f1["pairs"], f1["main"], config.min_frame_obs))
        if evidence["fired"]:
            k_app = config.appearance_neighbours if config.appearance_neighbours is not None \
                else config.auto_appearance_neighbours
            rounds = config.rematch_rounds if config.rematch_rounds is not None else config.auto_rematch_rounds
            evidence.update(appearance_neighbours=k_app, rematch_rounds=rounds)
            log(f"poor given poses: {evidence['message']}; matching again with {k_app} appearance neighbours "
                f"and {rounds} second-pass round(s)")
            P = matching_pass(k_app, rounds)
        else:
            evidence.update(appearance_neighbours=k_app, rematch_rounds=rounds)
            log(f"given poses good enough for distance neighbours: {evidence['message']}")
    neighbour_pairs, all_pairs, main, unmatched = P["neighbour_pairs"], P["all_pairs"], P["main"], P["unmatched"]
    T_out, rematched, pose_sigma = P["T_out"], P["rematched"], P["pose_sigma"]
    if unmatched and not config.keep_unmatched:
        raise AlignError(f"disconnected sequence: {len(unmatched)} frame(s) share no verified matches with the "
                         f"{len(main)} others: {_names(scene, unmatched)} (pass keep_unmatched / --keep-unmatched "
                         f"to keep their given poses)")

    # 7. per-frame acceptance; frames kept at their given pose anchor a re-adjustment of the others
    idx = sorted(main)
    status = {i: "given: unmatched" for i in unmatched}
    for i in idx:
        status[i] = "refined"
    frame_stats: dict[int, dict] = {}
    cov = np.full((n, 6, 6), np.nan)
    if all_pairs and idx:
        jpairs = [p for p in all_pairs if p[0] in main and p[1] in main]
        obs, _, slot = _pair_obs(jpairs, feats, scene, idx, config.max_matches_per_pair, config.seed + 2)
        K4 = _K4s(scene, idx)
        T_out, status, frame_stats, cov_m = _accept(T_given, T_out, idx, obs, K4, config, status)
        cov[idx] = cov_m
    t_end = time.perf_counter()

    e0, d0 = transfer_errors(all_pairs, feats, scene, T_given)
    e1, d1 = transfer_errors(all_pairs, feats, scene, T_out)
    dt, dr = pose_change(T_given, T_out)
    stats = {
        "frames": n, "groups": len(groups), "group_sizes": [1 + len(g.member_idxs) for g in groups],
        "local_pairs": len(local_pairs), "global_pairs": len(global_pairs),
        "neighbour_pairs": len(neighbour_pairs),
        "matches": int(sum(len(p[2].idx_a) for p in all_pairs)),
        "unmatched_frames": [scene.frame_ids[i] for i in unmatched],
        "rematched_frames": [scene.frame_ids[i] for i in sorted(set(rematched))],
        "auto_matching": evidence,
        "given_pose_sigma": (None if pose_sigma is None else
                             {"deg": float(np.degrees(pose_sigma[0])), "m": float(pose_sigma[1])}),
        "transfer_px_before": _stat(e0), "transfer_px_after": _stat(e1),
        "depth_res_m_before": _stat(d0), "depth_res_m_after": _stat(d1),
        "change_m": _stat(dt), "change_deg": _stat(dr),
        "per_frame_change": [{"frame_id": scene.frame_ids[i], "dt_m": float(dt[i]), "dr_deg": float(dr[i])}
                             for i in range(n)],
        "kept_given": {reason: [scene.frame_ids[i] for i in range(n) if status.get(i) == reason]
                       for reason in sorted({v for v in status.values() if v != "refined"})},
        "per_frame": [_frame_record(scene.frame_ids[i], status.get(i, "given: unmatched"), dt[i], dr[i],
                                    frame_stats.get(i, {}), cov[i]) for i in range(n)],
        "time_s": {"features": t_feat - t_start, "local_global": t_stages - t_feat,
                   "joint": t_end - t_stages, "total": t_end - t_start},
        "config": asdict(config),
    }
    n_kept = sum(1 for v in status.values() if v != "refined")
    if n_kept:
        log(f"kept the given pose of {n_kept} frame(s): " + "; ".join(
            f"{r} {len(v)} ({_names(scene, [scene.frame_ids.index(f) for f in v], 6)})"
            for r, v in stats["kept_given"].items()))
    log(f"aligned {n} frames: transfer error median {stats['transfer_px_before']['median']:.2f} -> "
        f"{stats['transfer_px_after']['median']:.2f} px, cameras moved median {np.median(dt) * 100:.2f} cm / "
        f"{np.median(dr):.2f} deg, {t_end - t_start:.1f} s")
    return AlignResult(T_out, stats)


def _weak_frames(n: int, pairs: list[Pair], main: set[int], min_frame_obs: int) -> list[int]:
    """Frames outside the connected set ``main`` or with fewer than ``min_frame_obs`` verified matches."""
    matched = np.zeros(n)
    for a, b, m in pairs:
        matched[a] += len(m.idx_a)
        matched[b] += len(m.idx_a)
    return [i for i in range(n) if i not in main or matched[i] < min_frame_obs]


def pose_noise_evidence(T_given: np.ndarray, T_refined: np.ndarray, pairs: list[tuple[int, int]],
                        frames: set[int] | list[int], k: int, fov_rad: float, max_ratio: float) -> dict:
    """Are the given poses too noisy for neighbours chosen by camera-centre distance? Pure.

    ``noise``: the robust spread (1.4826 x median absolute value, pooled over the axes) of the
    *relative* centre corrections ``(c_b - c_a)_refined - (c_b - c_a)_given`` over the verified pairs
    (a, b) among ``frames``: the per-axis noise of the vector between two given centres, which is
    what ranking frames by centre distance reads. Relative, so a smooth drift or a constant
    camera-to-marker offset (which leave the neighbour ranking intact) barely count, while noise
    independent per frame counts in full (sqrt(2) x the per-frame noise).
    ``spacing``: the median over ``frames`` of the distance from a refined camera centre to its
    ``k``-th nearest refined centre with the viewing direction within the FOV: the radius of the
    neighbourhood the distance-based choice picks from.
    ``fired`` when ``noise > max_ratio * spacing``. With ``max_ratio`` 0.25 (``AlignConfig``): the
    given distance between two frames is off by ``noise`` (1 sigma, along the line joining them), so
    its 95 % band (+-2 noise) is then wider than half the neighbourhood's radius: a typical true
    neighbour (half-way to the radius) is ranked outside the chosen set, and a frame from outside in
    it, at a rate of several per cent per neighbour, and distance no longer tells the frame's
    neighbourhood from the rest."""
    idx = sorted(frames)
    P = np.array(sorted({(min(a, b), max(a, b)) for a, b in pairs if a in frames and b in frames and a != b}),
                 dtype=int).reshape(-1, 2)
    c_r, c_g = T_refined[:, :3, 3], T_given[:, :3, 3]
    if len(P) == 0 or len(idx) < k + 1:
        return {"fired": False, "noise_m": None, "spacing_m": None, "ratio": None, "pairs": int(len(P)),
                "max_ratio": max_ratio, "message": "too few frames or pairs to measure the pose noise"}
    rel = (c_r[P[:, 1]] - c_r[P[:, 0]]) - (c_g[P[:, 1]] - c_g[P[:, 0]])
    noise = 1.4826 * float(np.median(np.abs(rel)))
    Ti = T_refined[idx]
    dk = []
    for a in range(len(idx)):
        ang = view_angles_rad(Ti, a)
        d = np.linalg.norm(Ti[:, :3, 3] - Ti[a, :3, 3], axis=1)
        d = np.sort(d[(np.arange(len(idx)) != a) & (ang <= fov_rad)])
        if len(d) >= k:
            dk.append(d[k - 1])
    spacing = float(np.median(dk)) if dk else float("nan")
    ratio = noise / spacing if spacing > 0 else float("inf")
    fired = bool(np.isfinite(spacing) and ratio > max_ratio)
    msg = (f"relative camera-centre noise {noise * 100:.2f} cm (robust, per axis, over {len(P)} verified pairs) "
           f"vs {k}-th-nearest-centre spacing {spacing * 100:.2f} cm: ratio {ratio:.2f} "
           f"{'>' if fired else '<='} {max_ratio:g}")
    return {"fired": fired, "noise_m": noise, "spacing_m": spacing, "ratio": float(ratio), "pairs": int(len(P)),
            "max_ratio": max_ratio, "message": msg}


def _given_pose_sigma(T_given: np.ndarray, T_out: np.ndarray, idx: list[int],
                      config: AlignConfig) -> tuple[float, float]:
    """(rad, m) noise of the given poses, 1 sigma per axis: as stated in ``config``, else the RMS per
    axis of the changes the first pass made to the frames ``idx`` (after the rigid fit)."""
    w = Rotation.from_matrix(np.einsum("nij,nkj->nik", T_out[idx, :3, :3], T_given[idx, :3, :3])).as_rotvec()
    v = T_out[idx, :3, 3] - T_given[idx, :3, 3]
    if config.pose_sigma_deg is not None and config.pose_sigma_m is not None:
        return float(np.radians(config.pose_sigma_deg)), float(config.pose_sigma_m)
    return float(np.sqrt(np.mean(np.sum(w * w, axis=1)) / 3)), float(np.sqrt(np.mean(np.sum(v * v, axis=1)) / 3))


def _rematch(weak: list[int], main: set[int], all_pairs: list[Pair], feats: list[Features], scene: Scene,
             T_out: np.ndarray, pose_sigma: tuple[float, float], sim: np.ndarray | None, k_app: int,
             fov: float, config: AlignConfig, pair_seed: int) -> tuple[list[Pair], dict[int, np.ndarray]]:
    """Second-pass pairs of the frames ``weak`` with frames of the connected set ``main`` (their
    ``rematch_neighbours`` nearest by the current poses within the FOV plus their
    ``k_app`` most similar), gated by :func:`match_pair` at the connected frame's
    refined pose (its error neglected: millimetres) and the weak frame's current pose with noise
    ``pose_sigma``. Pairs tried before under the fixed gate are tried again. Also the PnP pose (world
    frame of ``T_out``) of each weak frame outside ``main`` that found a pair (the pair with most
    inliers)."""
    n = len(T_out)
    have = {(min(a, b), max(a, b)) for a, b, _ in all_pairs}
    centres = T_out[:, :3, 3]
    sig = (pose_sigma[0], pose_sigma[1], 0.0, 0.0)
    out: list[Pair] = []
    best: dict[int, tuple[int, np.ndarray]] = {}
    for u in weak:
        ang = view_angles_rad(T_out, u)
        dist = np.linalg.norm(centres - centres[u], axis=1)
        cand = [int(j) for j in np.argsort(dist, kind="stable") if j in main and j != u and ang[j] <= fov]
        cand = cand[: config.rematch_neighbours]
        if sim is not None:
            cand += [int(j) for j in np.argsort(-sim[u], kind="stable") if j in main and j != u][:k_app]
        for j in dict.fromkeys(cand):
            if (min(u, j), max(u, j)) in have:
                continue
            have.add((min(u, j), max(u, j)))
            pm = match_pair(feats[u], feats[j], scene.intrinsics[u], scene.intrinsics[j], config.features,
                            seed=pair_seed + u * n + j, T_b_a_prior=_rel(T_out, u, j), prior_sigma=sig)
            if pm is None:
                continue
            out.append((u, j, pm))
            if u not in main and len(pm.idx_a) > best.get(u, (0, None))[0]:
                best[u] = (len(pm.idx_a), T_out[j] @ pm.T_b_a)  # T_world_u = T_world_j T_j_u
    return out, {u: T for u, (_, T) in best.items()}


def _rel(T_world_cam: np.ndarray, a: int, b: int) -> np.ndarray:
    """T_b_a: camera a -> camera b."""
    return invert_pose(T_world_cam[b]) @ T_world_cam[a]


def _restrict(f: Features, used: set[int] | None, fc: FeatureConfig) -> tuple[Features, np.ndarray]:
    """Features of a key image limited to those its local adjustment kept (thesis: the global feature
    group holds only locally used features); all features when too few were used (singleton groups)."""
    if not used or len(used) < 2 * fc.min_inliers:
        return f, np.arange(len(f.uv))
    idx = np.array(sorted(used))
    return Features(f.uv[idx], f.desc[idx], f.depth_m[idx]), idx


def _frame_test(T_given: np.ndarray, T_new: np.ndarray, obs: PairObservations, K4: np.ndarray,
                ba: BAConfig, accept_t: float) -> dict:
    """Per camera (local index) the acceptance statistics of ``T_new`` against ``T_given``:
    ``n_obs`` inlier observations touching it, ``n_pairs`` image pairs among them, ``t`` the paired t
    statistic of the per-observation reprojection cost decrease given -> new, ``t_depth`` the same
    for the depth cost (reported, not tested: see ``AlignConfig.accept_t``), ``t_pair`` as ``t`` with a
    cluster-robust standard error (the image pair as the cluster: for reference, it shows how much of
    the decrease is shared within pairs), ``chi2`` the frame's change under its own information,
    ``rms_given`` / ``rms_refined`` the RMS whitened residual, ``pairs_improved`` how many of its
    image pairs have a paired t statistic of their own reprojection cost decrease above ``accept_t``;
    and ``use``,
    the inlier mask (O,). An observation counts when it is an inlier under either pose set (neither
    side chooses its data)."""
    px_g, z_g, in_g = observation_costs(T_given, K4, obs, ba)
    px_n, z_n, in_n = observation_costs(T_new, K4, obs, ba)
    use = in_g | in_n
    C = len(T_given)
    d = px_g - px_n
    d_z = z_g - z_n
    rho_g, rho_n = px_g + z_g, px_n + z_n
    pair_key = obs.a_idx.astype(np.int64) * C + obs.b_idx
    # per image pair: paired t of the reprojection cost decrease over the pair's observations
    pk, p_of = np.unique(pair_key, return_inverse=True)
    w = use.astype(float)
    n_p = np.bincount(p_of, weights=w, minlength=len(pk))
    s1 = np.bincount(p_of, weights=w * d, minlength=len(pk))
    s2 = np.bincount(p_of, weights=w * d * d, minlength=len(pk))
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_p = s1 / n_p
        var_p = (s2 - n_p * mean_p ** 2) / (n_p - 1)
        t_p = mean_p / np.sqrt(np.maximum(var_p, 1e-300) / n_p)
    t_p = np.where(n_p >= 2, np.nan_to_num(t_p, nan=0.0), 0.0)
    improved_pair = t_p > accept_t
    pa, pb = pk // C, pk % C
    out = {k: np.zeros(C) for k in ("t", "t_pair", "t_depth")}
    out.update({k: np.zeros(C, int) for k in ("n_obs", "n_pairs", "pairs_improved")})
    out.update({k: np.full(C, np.nan) for k in ("rms_given", "rms_refined")})
    for c in range(C):
        m = use & ((obs.a_idx == c) | (obs.b_idx == c))
        k = int(m.sum())
        out["n_obs"][c] = k
        if k == 0:
            continue
        dm = d[m]
        out["rms_given"][c], out["rms_refined"][c] = np.sqrt(2 * rho_g[m].mean()), np.sqrt(2 * rho_n[m].mean())
        keys, pair_of = np.unique(pair_key[m], return_inverse=True)
        out["n_pairs"][c] = len(keys)
        out["pairs_improved"][c] = int(np.count_nonzero(improved_pair[((pa == c) | (pb == c)) & (n_p > 0)]))
        if k < 2:
            continue
        mean = float(dm.mean())
        se = float(np.std(dm, ddof=1)) / np.sqrt(k)
        se_pair = float(np.sqrt(np.sum(np.bincount(pair_of, weights=dm - mean) ** 2))) / k
        out["t"][c] = mean / se if se > 0 else (np.inf if mean > 0 else 0.0)
        out["t_pair"][c] = mean / se_pair if len(keys) > 1 and se_pair > 0 else np.nan
        dz = d_z[m]
        se_z = float(np.std(dz, ddof=1)) / np.sqrt(k)
        out["t_depth"][c] = float(dz.mean()) / se_z if se_z > 0 else 0.0
    # is the frame's own change measurable? chi2 of the change under its own information
    info = pose_information(T_new, K4, PairObservations(obs.a_idx[use], obs.b_idx[use], obs.X_a[use],
                                                        obs.uv_b[use], obs.z_b[use]), ba)
    w = Rotation.from_matrix(np.einsum("nij,nkj->nik", T_new[:, :3, :3], T_given[:, :3, :3])).as_rotvec()
    delta = np.concatenate([w, T_new[:, :3, 3] - T_given[:, :3, 3]], axis=1)
    out["chi2"] = np.einsum("ni,nij,nj->n", delta, info, delta)
    out["info"] = info
    out["use"] = use
    return out


_FRAME_KEYS = ("n_obs", "n_pairs", "pairs_improved", "t", "t_pair", "t_depth", "chi2", "rms_given", "rms_refined")


def _accept(T_given: np.ndarray, T_out: np.ndarray, idx: list[int], obs: PairObservations, K4: np.ndarray,
            config: AlignConfig, status: dict[int, str]):
    """Step 7 (see module doc) over the frames ``idx`` (global indices; ``obs`` uses local ones).
    Returns (poses, status, per-frame statistics, (len(idx), 6, 6) covariances)."""
    ba = config.ba
    Tg, Tn = T_given[idx], T_out[idx]
    C = len(idx)
    keep = np.zeros(C, bool)
    reason = [""] * C
    decided: dict[int, dict] = {}  # statistics of the round that kept a frame at its given pose
    few_all = np.zeros(C, bool)
    anchors_final = np.zeros(C, bool)
    for rnd in range(max(1, config.accept_rounds) + 1):
        ft = _frame_test(Tg, Tn, obs, K4, ba, config.accept_t)
        use = ft["use"]
        if config.accept_t <= 0:
            break
        few = ~keep & (ft["n_obs"] < config.min_frame_obs)
        weak = ~keep & ~few & ((ft["t"] <= config.accept_t) | (2 * ft["pairs_improved"] < ft["n_pairs"]))
        small = ~keep & ~few & ~weak & (ft["chi2"] <= config.accept_chi2)
        for c in np.flatnonzero(few):
            reason[c] = "given: few observations"
        for c in np.flatnonzero(weak):
            reason[c] = "given: residuals not significantly lower"
        for c in np.flatnonzero(small):
            reason[c] = "given: change within uncertainty"
        few_all |= few
        new_keep = keep | few | weak | small
        for c in np.flatnonzero(new_keep & ~keep):
            decided[c] = {k: ft[k][c] for k in _FRAME_KEYS}
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
        T_prev = Tn
        Tn = np.where(keep[:, None, None], Tg, Tn)
        if keep.all() or rnd == max(1, config.accept_rounds):
            break
        # Anchors: kept frames whose given pose the data confirm, i.e. the given pose lies inside the
        # frame's own confidence region once the refined trajectory is placed by the kept frames
        # (rigid fit onto them: the first fit also carried the frames being corrected). The others are
        # re-adjusted with the anchors fixed at their given poses, so no refined frame drifts relative
        # to a neighbour left at its given pose. Frames kept for lack of evidence (too few
        # observations, or a measurable change that does not lower the residuals) keep their given
        # pose but neither anchor nor constrain the others: measured on TUM fr1/rpy, anchoring at such
        # a frame's mocap pose (mocap-to-camera calibration error) bent its weakly matched neighbours
        # and cost one target 3.5 dB.
        cand = keep & ~few_all
        anchor = np.zeros(C, bool)
        if cand.any():
            S = fit_rigid_to(Tg[cand], T_prev[cand])
            anchor = cand & (_chi2_change(Tg, S @ T_prev, ft["info"]) <= config.accept_chi2)
            if anchor.any():
                S = fit_rigid_to(Tg[anchor], T_prev[anchor])
                Tn = np.where(keep[:, None, None], Tg, S @ T_prev)
        anchors_final = anchor
        loose = keep & ~anchor  # kept but not anchors: out of the re-adjustment
        m = use & ~loose[obs.a_idx] & ~loose[obs.b_idx] & ~(anchor[obs.a_idx] & anchor[obs.b_idx])
        touches_free = np.zeros(C, bool)
        touches_free[obs.a_idx[m]] = touches_free[obs.b_idx[m]] = True
        sub = PairObservations(obs.a_idx[m], obs.b_idx[m], obs.X_a[m], obs.uv_b[m], obs.z_b[m])
        if not m.any() or not (anchor & touches_free).any():
            # no anchor shares an observation with the free frames: the rigid fit stays their gauge
            Tn = np.where(keep[:, None, None], Tg, T_prev)
            continue
        res = adjust_poses(Tn, keep, K4, sub, ba)  # loose kept frames are fixed and unobserved
        Tn = res.T_world_cam
    ft = _frame_test(Tg, Tn, obs, K4, ba, config.accept_t)
    use = ft["use"]
    # uncertainty of the refined frames: relative to the anchors, else to the most observed refined frame
    anchor = anchors_final & keep
    loose = keep & ~anchor
    gauge = np.arange(C) == int(np.argmax(np.where(keep, -1, ft["n_obs"])))
    fixed = keep | (gauge if not anchor.any() else False)
    use = use & ~loose[obs.a_idx] & ~loose[obs.b_idx]
    inl = PairObservations(obs.a_idx[use], obs.b_idx[use], obs.X_a[use], obs.uv_b[use], obs.z_b[use])
    cov = pose_covariances(Tn, fixed, K4, inl, ba)
    frame_stats = {}
    for c, i in enumerate(idx):
        if keep[c]:
            status[i] = reason[c]
        src = decided[c] if keep[c] else {k: ft[k][c] for k in _FRAME_KEYS}
        frame_stats[i] = {k: (int(v) if k.startswith("n_") else float(v)) for k, v in src.items()}
    T = T_given.copy()
    T[idx] = Tn
    return T, status, frame_stats, cov


def _chi2_change(T_given: np.ndarray, T_new: np.ndarray, info: np.ndarray) -> np.ndarray:
    """(N,) chi2 of each frame's change (rotation vector, translation) from its given pose."""
    w = Rotation.from_matrix(np.einsum("nij,nkj->nik", T_new[:, :3, :3], T_given[:, :3, :3])).as_rotvec()
    delta = np.concatenate([w, T_new[:, :3, 3] - T_given[:, :3, 3]], axis=1)
    return np.einsum("ni,nij,nj->n", delta, info, delta)


def _frame_record(frame_id: str, status: str, dt: float, dr: float, fs: dict, cov: np.ndarray) -> dict:
    rec = {"frame_id": frame_id, "status": status, "dt_m": float(dt), "dr_deg": float(dr)}
    for k in _FRAME_KEYS:
        if k in fs:
            v = fs[k]
            rec[k] = v if isinstance(v, int) else (round(v, 4) if np.isfinite(v) else None)
    if np.all(np.isfinite(cov)):
        rec["sigma_rot_deg"] = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
        rec["sigma_trans_m"] = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
    return rec
