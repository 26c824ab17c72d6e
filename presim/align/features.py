"""SIFT features with depth, and verified matches between two RGB-D frames (thesis §5.3.3).

Verification uses the RGB-D data instead of a fundamental matrix: the first frame's matched keypoints
are lifted to 3D with its depth and a PnP RANSAC fits the second frame's keypoints. A fundamental
matrix degenerates when the camera only rotates (TUM ``fr1/rpy``); PnP does not, and its inliers are
exactly the matches the bundle adjustment can use (landmarks need depth in the key frame).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from presim.geometry import Intrinsics, project, unproject

__all__ = ["FeatureConfig", "Features", "PairMatch", "appearance_similarity", "extract_features", "match_pair",
           "predicted_match_cov", "unproject_uv"]


@dataclass(frozen=True)
class FeatureConfig:
    max_features: int = 2000
    """SIFT keypoints kept per image (strongest first)."""
    ratio: float = 0.8
    """Lowe's ratio test: best / second-best descriptor distance below this."""
    ransac_px: float = 3.0
    """PnP RANSAC inlier threshold, pixels."""
    ransac_iters: int = 2000
    """P3P RANSAC iterations: 20 % inliers (repetitive texture) still succeed with p ~ 0.96."""
    prior_px: float | None = 80.0
    """When the caller passes a prior relative pose (alignment of given poses), ratio-test matches
    farther than this from where the prior puts them are dropped before RANSAC (repetitive texture
    otherwise swamps the inliers). None = no gating. 80 px ~ 8 deg at fx 540: above the error of
    drifting SLAM/mocap poses."""
    gate_chi2: float = 13.82
    """With a pose uncertainty for the prior (``match_pair(prior_sigma=...)``), a candidate is kept when
    its offset from the predicted position is inside this Mahalanobis radius squared under the
    predicted-match covariance (:func:`predicted_match_cov`); 13.82 = 99.9 % of chi-square with 2
    degrees of freedom."""
    min_inliers: int = 20
    """A pair with fewer verified matches is not used."""
    max_depth_jump: float = 0.03
    """A keypoint's depth (median of the valid pixels of its 3x3 window, at least 3) is kept only
    when those span less than this fraction of it (drops flying pixels on depth edges)."""


@dataclass(frozen=True)
class Features:
    uv: np.ndarray
    """(M, 2) float32 pixel coordinates (pixel centres at integers)."""
    desc: np.ndarray
    """(M, 128) uint8 SIFT descriptors."""
    depth_m: np.ndarray
    """(M,) float32 z-depth at the keypoint, 0 = none."""


@dataclass(frozen=True)
class PairMatch:
    idx_a: np.ndarray
    """(K,) indices into the first frame's features (all with depth)."""
    idx_b: np.ndarray
    """(K,) indices into the second frame's features."""
    T_b_a: np.ndarray
    """(4, 4) PnP estimate of the second camera from the first (maps camera-a points to camera b)."""


def unproject_uv(K: Intrinsics, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """(M, 3) camera-frame points of pixels ``uv`` (M, 2) at z-depth ``depth_m`` (M,) (geometry.unproject)."""
    return unproject(K, uv, depth_m)


def extract_features(color: np.ndarray, depth_m: np.ndarray, config: FeatureConfig = FeatureConfig()) -> Features:
    """SIFT keypoints and descriptors of an RGB uint8 (H, W, 3) image, with the depth at each keypoint."""
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"color must be uint8 (H, W, 3), got {color.dtype} {color.shape}")
    gray = cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(nfeatures=config.max_features)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8), np.zeros(0, np.float32))
    uv = np.array([k.pt for k in kps], dtype=np.float32)  # OpenCV keypoints: pixel centres at integers, as ours
    h, w = depth_m.shape
    iu = np.clip(np.floor(uv[:, 0] + 0.5).astype(int), 0, w - 1)
    iv = np.clip(np.floor(uv[:, 1] + 0.5).astype(int), 0, h - 1)
    d = np.asarray(depth_m, dtype=np.float32)
    pad = np.pad(d, 1, mode="edge")
    win = np.stack([pad[iv + dy, iu + dx] for dy in range(3) for dx in range(3)], axis=1)
    # Registered depth often has a hole pattern (a depth pixel lands on every other color pixel): take
    # the median of the valid pixels of the 3x3 window when at least 3 are valid and they agree.
    valid = win > 0
    cnt = valid.sum(axis=1)
    w_nan = np.where(valid, win, np.nan)
    with warnings.catch_warnings():  # all-NaN windows (no valid depth) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        z = np.nanmedian(w_nan, axis=1)
        spread = np.nanmax(w_nan, axis=1) - np.nanmin(w_nan, axis=1)
    ok = (cnt >= 3) & (spread < config.max_depth_jump * np.nan_to_num(z, nan=0.0))
    z = np.nan_to_num(z, nan=0.0)
    # SIFT descriptors are integers 0..255: uint8 keeps 180 frames x 2000 features at 46 MB.
    return Features(uv, np.clip(np.rint(desc), 0, 255).astype(np.uint8), np.where(ok, z, 0.0).astype(np.float32))


def predicted_match_cov(K_b: Intrinsics, X_a: np.ndarray, T_b_a: np.ndarray,
                        prior_sigma: tuple[float, float, float, float], sigma_px: float) -> np.ndarray:
    """(M, 2, 2) covariance of where points ``X_a`` (M, 3, camera a) appear in image b under the
    relative pose ``T_b_a``, when each camera's pose is off by independent isotropic noise
    ``prior_sigma = (rot_a rad, trans_a m, rot_b rad, trans_b m)`` (1 sigma per axis), plus
    ``sigma_px`` of feature noise.

    A rotation error w of camera a about its centre moves the point in b's frame by R_ba (w x p_a),
    covariance ``rot_a^2 (|q|^2 I - q q^T)`` with q = R_ba p_a; a centre error adds ``trans_a^2 I``;
    camera b's errors likewise with x = the point in b's frame. Mapped to pixels by the projection's
    Jacobian (first order)."""
    sra, sta, srb, stb = (float(v) for v in prior_sigma)
    X_a = np.asarray(X_a, np.float64)
    q = X_a @ T_b_a[:3, :3].T
    x = q + T_b_a[:3, 3]
    eye = np.eye(3)[None]

    def rot_cov(p: np.ndarray, s: float) -> np.ndarray:
        return s * s * (np.einsum("mi,mi->m", p, p)[:, None, None] * eye - p[:, :, None] * p[:, None, :])

    S3 = rot_cov(q, sra) + rot_cov(x, srb) + (sta * sta + stb * stb) * eye
    z = np.where(np.abs(x[:, 2]) > 1e-9, x[:, 2], 1e-9)
    J = np.zeros((len(x), 2, 3))
    J[:, 0, 0] = K_b.fx / z
    J[:, 0, 2] = -K_b.fx * x[:, 0] / z ** 2
    J[:, 1, 1] = K_b.fy / z
    J[:, 1, 2] = -K_b.fy * x[:, 1] / z ** 2
    return J @ S3 @ J.transpose(0, 2, 1) + sigma_px * sigma_px * np.eye(2)[None]


def match_pair(fa: Features, fb: Features, K_a: Intrinsics, K_b: Intrinsics,
               config: FeatureConfig = FeatureConfig(), seed: int = 0,
               T_b_a_prior: np.ndarray | None = None,
               prior_sigma: tuple[float, float, float, float] | None = None) -> PairMatch | None:
    """Verified matches from frame a (with depth) to frame b, or None when fewer than ``min_inliers``.

    ``T_b_a_prior``: an approximate relative pose (camera a -> camera b); with ``config.prior_px`` it
    gates the candidate matches (see :class:`FeatureConfig`). With ``prior_sigma`` (each camera's pose
    noise, see :func:`predicted_match_cov`) the gate is instead the Mahalanobis radius
    ``config.gate_chi2`` under the predicted-match covariance: it grows with the poses' uncertainty
    and with the point's nearness."""
    if len(fa.uv) < 2 or len(fb.uv) < 2:
        return None
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    knn = matcher.knnMatch(fa.desc.astype(np.float32), fb.desc.astype(np.float32), k=2)
    ia, ib = [], []
    for m in knn:
        if len(m) == 2 and m[0].distance < config.ratio * m[1].distance and fa.depth_m[m[0].queryIdx] > 0:
            ia.append(m[0].queryIdx)
            ib.append(m[0].trainIdx)
    if len(ia) < config.min_inliers:
        return None
    ia_a, ib_a = np.array(ia), np.array(ib)
    # One keypoint of b matched from several of a: keep none of them (ambiguous).
    uniq, cnt = np.unique(ib_a, return_counts=True)
    keep = np.isin(ib_a, uniq[cnt == 1])
    ia_a, ib_a = ia_a[keep], ib_a[keep]
    if len(ia_a) < config.min_inliers:
        return None
    X = unproject_uv(K_a, fa.uv[ia_a].astype(np.float64), fa.depth_m[ia_a].astype(np.float64))
    if T_b_a_prior is not None and (config.prior_px is not None or prior_sigma is not None):
        uv_pred, z = project(K_b, X @ T_b_a_prior[:3, :3].T + T_b_a_prior[:3, 3])
        r = np.nan_to_num(uv_pred, nan=1e9) - fb.uv[ib_a]
        if prior_sigma is not None:
            C = predicted_match_cov(K_b, X, T_b_a_prior, prior_sigma, config.ransac_px)
            d2 = np.einsum("mi,mij,mj->m", r, np.linalg.inv(C), r)
            near = (z > 0) & (d2 <= config.gate_chi2)
        else:
            near = (z > 0) & (np.linalg.norm(r, axis=1) < config.prior_px)
        ia_a, ib_a, X = ia_a[near], ib_a[near], X[near]
        if len(ia_a) < config.min_inliers:
            return None
    cv2.setRNGSeed(int(seed))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, fb.uv[ib_a].astype(np.float64), K_b.K, None,
                                             iterationsCount=config.ransac_iters,
                                             reprojectionError=config.ransac_px, confidence=0.999,
                                             flags=cv2.SOLVEPNP_P3P)
    if not ok or inl is None or len(inl) < config.min_inliers:
        return None
    inl = inl.ravel()
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return PairMatch(ia_a[inl], ib_a[inl], T)


def appearance_similarity(descriptors: list[np.ndarray], words: int = 256, seed: int = 0,
                          per_frame: int = 200) -> np.ndarray:
    """(N, N) cosine similarity of the frames' TF-IDF bag-of-words histograms (diagonal included).

    The vocabulary is ``words`` k-means centres (10 Lloyd iterations, seeded) of at most ``per_frame``
    descriptors per frame (a seeded subset): a vocabulary learnt on the capture itself, since none can
    be downloaded. It depends on the images only, never on the poses: which frames are matched does
    not inherit the errors of the poses being refined. ``descriptors``: one (M_i, 128) array per frame.
    Deterministic for ``seed``."""
    n = len(descriptors)
    rng = np.random.default_rng(seed)
    sample = []
    for d in descriptors:
        sel = rng.choice(len(d), min(len(d), per_frame), replace=False) if len(d) else np.zeros(0, int)
        sample.append(np.asarray(d)[np.sort(sel)].astype(np.float32))
    sample = np.concatenate(sample) if sample else np.zeros((0, 128), np.float32)
    words = min(words, len(sample))
    if words < 2:
        return np.zeros((n, n))
    centres = sample[rng.choice(len(sample), words, replace=False)]

    def assign(x: np.ndarray) -> np.ndarray:
        d2 = (x * x).sum(1)[:, None] - 2 * x @ centres.T + (centres * centres).sum(1)[None]
        return np.argmin(d2, axis=1)

    for _ in range(10):
        lab = assign(sample)
        for w in range(words):
            m = lab == w
            if m.any():
                centres[w] = sample[m].mean(0)
    hist = np.zeros((n, words))
    for i, d in enumerate(descriptors):
        if len(d):
            hist[i] = np.bincount(assign(np.asarray(d).astype(np.float32)), minlength=words)
    idf = np.log(n / np.maximum(1, (hist > 0).sum(0)))
    v = hist / np.maximum(1, hist.sum(1, keepdims=True)) * idf
    v /= np.maximum(1e-12, np.linalg.norm(v, axis=1, keepdims=True))
    return v @ v.T
