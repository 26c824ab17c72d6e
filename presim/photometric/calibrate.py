"""Photometric calibration of a capture: one colour transform per frame, solved jointly (beyond the thesis).

Auto-exposure and auto-white-balance change between the frames of a real capture, so a pixel warped
from one view does not have the colour the same surface has in another. This module estimates, for
every frame ``i``, a per-channel gain and bias of the forward model

    observed_i(x) = gain_i * radiance(x) + bias_i        (8-bit levels, per channel)

where ``radiance`` is the colour the surface has at the capture's *mean exposure*: the solution is
anchored so that the mean gain over the frames is 1 and the mean bias is 0 (the overall exposure
stays where the capture put it; a capture of identical frames gets the identity everywhere).

How (:func:`calibrate_photometric`):

1. **Pairs**: each frame is paired with its ``num_neighbors`` nearest frames by camera centre whose
   optical axes are within ``max_angle_deg`` (unordered pairs, each once).
2. **Correspondences by depth reprojection**: every ``stride_px``-th pixel of frame i with depth
   (refined when the scene has it) is unprojected to the world and projected into frame j
   (``presim.geometry``), landing on j's nearest pixel (:func:`capture.reprojection.nearest_pixel`);
   it is kept when j's depth there agrees with the projected depth within ``depth_tol_rel``
   (occlusion / misregistration test), when no channel is clipped (``<= clip_lo`` or ``>= clip_hi``
   in either image) and when the local gradient is small (lowest ``keep_gradient_frac`` of the
   pair's samples: a pose error of a pixel moves a colour edge, not a flat patch). Colours are read
   from images blurred with a Gaussian of ``blur_sigma_px`` (an exposure change is global, a blur
   only suppresses misalignment and noise).
3. **Joint linear least squares** in the inverse model ``radiance = a_i * observed_i + c_i``: every
   correspondence gives one row ``a_i x_i + c_i - a_j x_j - c_j = 0``; the anchor rows
   ``mean(a) = 1``, ``mean(c) = 0`` (heavily weighted) and a weak ridge towards the identity (keeps
   a frame without any correspondence at the identity) complete the system. The normal equations
   are 2N x 2N per channel, accumulated with ``bincount`` over the samples; ``irls_iters`` rounds of
   Huber re-weighting (threshold ``huber_k`` x the MAD scale) discount moving objects, specularities
   and leftover misalignment.
4. The inverse model is turned back into ``gain = 1/a``, ``bias = -c/a`` and re-anchored exactly
   (mean gain 1, mean bias 0).

The result (:class:`presim.capture.calibration.PhotometricCalib`, a leaf type the scene and the
renderer read) is keyed by frame id, so ``Scene.subset`` keeps it valid; it
is stored with the scene as ``photometric.json`` (:func:`presim.capture.store.save_photometric`)
and applied at render time by :mod:`presim.photometric.apply`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from presim.capture.calibration import PHOTOMETRIC_MODELS, PhotometricCalib, vignetting_radius_sq
from presim.capture.reprojection import nearest_pixel
from presim.geometry import invert, project, unproject_depth
from presim.io_utils import progress

__all__ = ["PhotometricConfig", "calibrate_photometric", "photometric_pairs", "pair_correspondences"]

@dataclass(frozen=True)
class PhotometricConfig:
    """Knobs of :func:`calibrate_photometric`."""

    model: str = "gain_bias"
    """``"gain_bias"`` (per-channel gain and bias), ``"gain"`` (per-channel gain, bias fixed at 0) or
    ``"affine"`` (a 3x3 colour matrix and a bias per frame: white balance / colour mixing)."""
    vignetting: bool = False
    """Also solve one radial vignetting term shared by all frames (:class:`PhotometricCalib`
    ``vignetting``), jointly with the per-frame transforms (alternating rounds)."""
    vignetting_rounds: int = 6
    """Alternations between the per-frame transforms and the shared vignetting term."""
    num_neighbors: int = 6
    """Each frame is paired with this many nearest frames (camera centre distance)."""
    max_angle_deg: float = 45.0
    """Pairs whose optical axes differ by more than this are not used."""
    stride_px: int = 4
    """Every ``stride_px``-th pixel (both axes) of a frame is a correspondence candidate."""
    depth_tol_rel: float = 0.03
    """A reprojected point is kept when the other frame's depth agrees within this fraction."""
    blur_sigma_px: float = 2.0
    """Gaussian blur of the images before colours are read (0 = none)."""
    keep_gradient_frac: float = 0.6
    """Keep the samples of a pair whose blurred-gradient magnitude is in this lowest fraction."""
    clip_lo: int = 3
    """Samples with a channel <= this (crushed blacks) in either image are dropped."""
    clip_hi: int = 250
    """Samples with a channel >= this (saturated) in either image are dropped."""
    max_samples_per_pair: int = 4000
    """Random subsample of each pair's correspondences (bounds time and memory)."""
    irls_iters: int = 4
    """Huber re-weighting rounds after the first least-squares solve."""
    huber_k: float = 2.0
    """Huber threshold in units of the robust (MAD) residual scale."""
    ridge: float = 1e-3
    """Weight of the pull towards the identity, relative to a frame's number of samples."""
    use_refined_depth: bool = True
    """Use ``scene.depth_refined`` for the correspondences when present."""
    seed: int = 0
    """Seed of the sample subsampling."""

    def __post_init__(self) -> None:
        if self.model not in PHOTOMETRIC_MODELS:
            raise ValueError(f"PhotometricConfig: model must be one of {PHOTOMETRIC_MODELS}")
        if self.vignetting_rounds < 1:
            raise ValueError("PhotometricConfig: vignetting_rounds must be >= 1")
        if self.num_neighbors < 1 or self.stride_px < 1:
            raise ValueError("PhotometricConfig: num_neighbors and stride_px must be >= 1")
        if not 0.0 < self.keep_gradient_frac <= 1.0:
            raise ValueError("PhotometricConfig: keep_gradient_frac must be in (0, 1]")
        if not 0.0 < self.depth_tol_rel < 1.0:
            raise ValueError("PhotometricConfig: depth_tol_rel must be in (0, 1)")


def photometric_pairs(T_world_cam: np.ndarray, num_neighbors: int, max_angle_deg: float) -> list[tuple[int, int]]:
    """Unordered frame pairs ``(i, j)``, ``i < j``: each frame with its nearest frames by centre
    distance whose optical axes are within ``max_angle_deg``."""
    T = np.asarray(T_world_cam, np.float64)
    c = T[:, :3, 3]
    z = T[:, :3, 2] / np.linalg.norm(T[:, :3, 2], axis=1, keepdims=True)
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    cos = np.clip(z @ z.T, -1.0, 1.0)
    d[np.degrees(np.arccos(cos)) > max_angle_deg] = np.inf
    np.fill_diagonal(d, np.inf)
    pairs = set()
    for i in range(len(T)):
        for j in np.argsort(d[i], kind="stable")[:num_neighbors]:
            if np.isfinite(d[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _blurred(color: np.ndarray, sigma: float) -> np.ndarray:
    f = color.astype(np.float32)
    return cv2.GaussianBlur(f, (0, 0), sigma) if sigma > 0 else f


def _gradient(img_f: np.ndarray) -> np.ndarray:
    g = img_f.mean(axis=2)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.sqrt(gx * gx + gy * gy)


def pair_correspondences(raw_i: np.ndarray, blur_i: np.ndarray, grad_i: np.ndarray, depth_i: np.ndarray,
                         raw_j: np.ndarray, blur_j: np.ndarray, grad_j: np.ndarray, depth_j: np.ndarray,
                         K_i, K_j, T_j_i: np.ndarray, config: PhotometricConfig,
                         rng: np.random.Generator, with_pixels: bool = False) -> tuple[np.ndarray, ...]:
    """Colours ``(x_i, x_j)`` (float32 (m, 3) each, blurred images) of the same surface points seen
    in frames i and j (step 2 of the module docstring); ``with_pixels`` adds their pixel positions
    ``(uv_i, uv_j)`` (float64 (m, 2) each)."""
    def empty():
        e = np.zeros((0, 3), np.float32)
        return (e, e, np.zeros((0, 2)), np.zeros((0, 2))) if with_pixels else (e, e)

    s = config.stride_px
    pts, mask = unproject_depth(K_i, depth_i, T_j_i, stride=s)
    if len(pts) == 0:
        return empty()
    vv, uu = np.nonzero(mask)
    vi, ui = vv * s, uu * s
    uv, z = project(K_j, pts)
    uj, vj, inside = nearest_pixel(uv, K_j.width, K_j.height)
    ok = inside & (z > 0)
    dj = depth_j[vj, uj]
    ok &= (dj > 0) & (np.abs(dj - z) <= config.depth_tol_rel * z)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return empty()
    vi, ui, vj, uj, uvj = vi[idx], ui[idx], vj[idx], uj[idx], uv[idx]
    ri, rj = raw_i[vi, ui], raw_j[vj, uj]
    ok = ((ri > config.clip_lo) & (ri < config.clip_hi) & (rj > config.clip_lo) & (rj < config.clip_hi)).all(axis=1)
    vi, ui, vj, uj, uvj = vi[ok], ui[ok], vj[ok], uj[ok], uvj[ok]
    if len(vi) == 0:
        return empty()
    g = np.maximum(grad_i[vi, ui], grad_j[vj, uj])
    if config.keep_gradient_frac < 1.0 and len(g) > 10:
        keep = g <= np.quantile(g, config.keep_gradient_frac)
        vi, ui, uvj = vi[keep], ui[keep], uvj[keep]
    if len(vi) > config.max_samples_per_pair:
        sel = rng.choice(len(vi), config.max_samples_per_pair, replace=False)
        vi, ui, uvj = vi[sel], ui[sel], uvj[sel]
    xi, xj = blur_i[vi, ui], _bilinear(blur_j, uvj)
    if with_pixels:
        return xi, xj, np.stack([ui, vi], axis=1).astype(np.float64), np.asarray(uvj, np.float64)
    return xi, xj


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` (H, W, C) at sub-pixel ``uv`` (m, 2) (pixel centres at integers)."""
    H, W = img.shape[:2]
    u = np.clip(uv[:, 0], 0, W - 1.001)
    v = np.clip(uv[:, 1], 0, H - 1.001)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    return ((1 - fv) * ((1 - fu) * img[v0, u0] + fu * img[v0, u0 + 1])
            + fv * ((1 - fu) * img[v0 + 1, u0] + fu * img[v0 + 1, u0 + 1])).astype(np.float32)


def _solve_channel(xi: np.ndarray, xj: np.ndarray, pi: np.ndarray, pj: np.ndarray, n: int,
                   config: PhotometricConfig) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Inverse model ``radiance = a * x + c`` for one channel: returns ``(a, c, rms0, rms1)``."""
    nv = 2 * n
    # Row coefficients: +x at a_i, +1 at c_i, -y at a_j, -1 at c_j.
    cols = np.stack([pi, n + pi, pj, n + pj], axis=1)
    vals = np.stack([xi, np.ones_like(xi), -xj, -np.ones_like(xj)], axis=1).astype(np.float64)
    counts = np.bincount(np.concatenate([pi, pj]), minlength=n).astype(np.float64)
    w = np.ones(len(xi))
    rms0 = float(np.sqrt(np.mean((xi - xj) ** 2))) if len(xi) else 0.0
    scale_x = 128.0  # a's coefficients are levels; keep the ridge/anchor on a comparable scale
    a = np.ones(n)
    c = np.zeros(n)
    for it in range(config.irls_iters + 1):
        AtA = np.zeros((nv, nv))
        if len(xi):
            for p in range(4):
                for q in range(4):
                    key = cols[:, p] * nv + cols[:, q]
                    AtA += np.bincount(key, weights=w * vals[:, p] * vals[:, q], minlength=nv * nv).reshape(nv, nv)
        Atb = np.zeros(nv)
        # Ridge towards the identity (a = 1, c = 0), relative to each frame's sample count.
        lam = config.ridge * np.maximum(counts, 1.0)
        AtA[np.arange(n), np.arange(n)] += lam * scale_x ** 2
        Atb[:n] += lam * scale_x ** 2
        AtA[n + np.arange(n), n + np.arange(n)] += lam if config.model == "gain_bias" else 1e6 * np.maximum(counts, 1.0)
        # Anchor rows: mean(a) = 1 and mean(c) = 0, weighted far above the data.
        big = 1e3 * max(float(counts.sum()), 1.0)
        ra = np.zeros(nv)
        ra[:n] = scale_x / n
        AtA += big * np.outer(ra, ra)
        Atb += big * ra * scale_x
        rc = np.zeros(nv)
        rc[n:] = 1.0 / n
        AtA += big * np.outer(rc, rc)
        sol = np.linalg.solve(AtA, Atb)
        a, c = sol[:n], sol[n:]
        if not len(xi) or it == config.irls_iters:
            break
        r = a[pi] * xi + c[pi] - a[pj] * xj - c[pj]
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-6
        thr = config.huber_k * sigma
        ar = np.abs(r)
        w = np.where(ar <= thr, 1.0, thr / np.maximum(ar, 1e-12))
    rms1 = float(np.sqrt(np.mean((a[pi] * xi + c[pi] - a[pj] * xj - c[pj]) ** 2))) if len(xi) else 0.0
    return a, c, rms0, rms1


def _solve_general(Fi: np.ndarray, Fj: np.ndarray, pi: np.ndarray, pj: np.ndarray, segs: list, n: int,
                   ident: np.ndarray, bias_fixed: bool, config: PhotometricConfig) -> tuple[np.ndarray, np.ndarray]:
    """One output channel of the inverse model ``radiance = theta_k . F`` (features ``F`` (m, p): the
    colour terms, last the bias term), rows ``theta_i . F_i - theta_j . F_j = 0`` with the anchor
    ``mean_k theta_k = ident``, a ridge towards ``ident`` and Huber IRLS (as :func:`_solve_channel`).
    The normal equations are accumulated per pair (``segs``: ``(start, end, i, j)`` sample ranges).
    Returns ``(theta (n, p), final sample weights (m,))``."""
    p = Fi.shape[1]
    nv = n * p
    scale = np.full(p, 128.0)  # colour-term parameters multiply levels; keep ridge/anchor comparable
    scale[-1] = 1.0
    counts = np.bincount(np.concatenate([pi, pj]), minlength=n).astype(np.float64)
    w = np.ones(len(Fi))
    ar = np.arange(p)
    theta = np.tile(ident, (n, 1))
    for it in range(config.irls_iters + 1):
        AtA = np.zeros((nv, nv))
        for s0, s1, i, j in segs:
            X = np.concatenate([Fi[s0:s1], -Fj[s0:s1]], axis=1)
            ii = np.concatenate([i * p + ar, j * p + ar])
            AtA[np.ix_(ii, ii)] += X.T @ (X * w[s0:s1, None])
        Atb = np.zeros(nv)
        lam = config.ridge * np.maximum(counts, 1.0)
        big = 1e3 * max(float(counts.sum()), 1.0)
        for q in range(p):
            idx = np.arange(n) * p + q
            fixed = bias_fixed and q == p - 1
            AtA[idx, idx] += 1e6 * np.maximum(counts, 1.0) if fixed else lam * scale[q] ** 2
            Atb[idx] += 0.0 if fixed else lam * scale[q] ** 2 * ident[q]
            ra = np.zeros(nv)
            ra[idx] = scale[q] / n
            AtA += big * np.outer(ra, ra)
            Atb += big * ra * scale[q] * ident[q]
        theta = np.linalg.solve(AtA, Atb).reshape(n, p)
        if not len(Fi) or it == config.irls_iters:
            break
        r = np.sum(theta[pi] * Fi, axis=1) - np.sum(theta[pj] * Fj, axis=1)
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-6
        thr = config.huber_k * sigma
        w = np.where(np.abs(r) <= thr, 1.0, thr / np.maximum(np.abs(r), 1e-12))
    return theta, w


def _calibrate_general(xi, xj, pi, pj, r2i, r2j, segs, n, config: PhotometricConfig):
    """Affine and/or vignetting models (step 3 generalised): alternates the per-frame inverse
    transforms ``radiance = W(r) (M_k x + c_k)`` (``W = 1 + k1 r^2 + k2 r^4``, linear in ``M, c``
    for fixed ``W``) and the shared ``(k1, k2)`` (linear for fixed ``M, c``). Returns forward
    ``(A (n, 3, 3), b (n, 3), (k1, k2), rms_after (3,))``."""
    affine = config.model == "affine"
    k1 = k2 = 0.0
    M = np.tile(np.eye(3), (n, 1, 1))
    c = np.zeros((n, 3))
    rounds = config.vignetting_rounds if config.vignetting else 1
    ones = np.ones((len(xi), 1))
    for rd in range(rounds):
        Wi = (1.0 + k1 * r2i + k2 * r2i ** 2)[:, None]
        Wj = (1.0 + k1 * r2j + k2 * r2j ** 2)[:, None]
        weights = []
        for ch in range(3):
            if affine:
                Fi, Fj = np.concatenate([xi * Wi, Wi], 1), np.concatenate([xj * Wj, Wj], 1)
                ident = np.r_[np.eye(3)[ch], 0.0]
            else:
                Fi, Fj = np.concatenate([xi[:, ch:ch + 1] * Wi, Wi], 1), np.concatenate([xj[:, ch:ch + 1] * Wj, Wj], 1)
                ident = np.array([1.0, 0.0])
            theta, w = _solve_general(Fi, Fj, pi, pj, segs, n, ident, config.model == "gain", config)
            if affine:
                M[:, ch, :] = theta[:, :3]
            else:
                M[:, ch, ch] = theta[:, 0]
            c[:, ch] = theta[:, -1]
            weights.append(w)
        if not config.vignetting or rd == rounds - 1 or not len(xi):
            break
        # Shared vignetting for fixed transforms: y_i W_i - y_j W_j = 0, linear in (k1, k2).
        yi = np.einsum("mab,mb->ma", M[pi], xi) + c[pi]
        yj = np.einsum("mab,mb->ma", M[pj], xj) + c[pj]
        B = np.stack([yi * r2i[:, None] - yj * r2j[:, None], yi * r2i[:, None] ** 2 - yj * r2j[:, None] ** 2], -1)
        rhs = -(yi - yj)
        wt = np.stack(weights, 1)
        BtB = np.einsum("mck,mc,mcl->kl", B, wt, B)
        Btr = np.einsum("mck,mc,mc->k", B, wt, rhs)
        k1, k2 = np.linalg.solve(BtB + 1e-9 * np.eye(2) * max(np.trace(BtB), 1.0), Btr)
    Wi = (1.0 + k1 * r2i + k2 * r2i ** 2)[:, None]
    Wj = (1.0 + k1 * r2j + k2 * r2j ** 2)[:, None]
    res = Wi * (np.einsum("mab,mb->ma", M[pi], xi) + c[pi]) - Wj * (np.einsum("mab,mb->ma", M[pj], xj) + c[pj])
    rms1 = np.sqrt(np.mean(res ** 2, axis=0)) if len(xi) else np.zeros(3)
    A = np.linalg.inv(M)
    b = -np.einsum("nab,nb->na", A, c)
    # Exact re-anchoring (radiance' = S radiance [+ t]): mean A = I (and mean b = 0 without
    # vignetting; with it a shift is not a per-frame affine map, the anchor rows keep it near 0).
    S = A.mean(axis=0)
    A = A @ np.linalg.inv(S)
    if not config.vignetting:
        b = b - A @ b.mean(axis=0)
    return A, b, (float(k1), float(k2)), rms1


def calibrate_photometric(scene, config: PhotometricConfig = PhotometricConfig(),
                          show_progress: bool = True) -> PhotometricCalib:
    """Per-frame gain and bias of every frame of ``scene`` (see the module docstring).

    Args:
        scene: a :class:`presim.capture.scene.Scene` with poses and depth.
        config: :class:`PhotometricConfig`.
    Returns:
        :class:`PhotometricCalib` with one row per frame (mean gain 1, mean bias 0).
    """
    t0 = time.perf_counter()
    n = len(scene)
    pairs = photometric_pairs(scene.T_world_cam, config.num_neighbors, config.max_angle_deg)
    rng = np.random.default_rng(config.seed)
    cache: dict[int, tuple] = {}  # pairs come sorted by i: frames below the current i are done

    def get(k: int):
        if k not in cache:
            color, depth = scene.frames.load(k)
            if config.use_refined_depth and scene.depth_refined is not None:
                depth = np.asarray(scene.depth_refined[k])
            b = _blurred(color, config.blur_sigma_px)
            cache[k] = (np.asarray(color), b, _gradient(b), np.asarray(depth, np.float32))
        return cache[k]

    general = config.model == "affine" or config.vignetting
    xs_i, xs_j, ps_i, ps_j, r2s_i, r2s_j, segs = [], [], [], [], [], [], []
    m = 0
    T_cam_world = [invert(T) for T in scene.T_world_cam]
    it = progress(pairs, desc="photometric pairs", unit="pair") if show_progress else pairs
    for i, j in it:
        fi, fj = get(i), get(j)
        T_j_i = T_cam_world[j] @ scene.T_world_cam[i]
        got = pair_correspondences(fi[0], fi[1], fi[2], fi[3], fj[0], fj[1], fj[2], fj[3],
                                   scene.intrinsics[i], scene.intrinsics[j], T_j_i, config, rng, with_pixels=general)
        a, b = got[0], got[1]
        if len(a):
            if general:
                r2s_i.append(vignetting_radius_sq(got[2], scene.intrinsics[i]))
                r2s_j.append(vignetting_radius_sq(got[3], scene.intrinsics[j]))
                segs.append((m, m + len(a), i, j))
                m += len(a)
            xs_i.append(a)
            xs_j.append(b)
            ps_i.append(np.full(len(a), i, np.int64))
            ps_j.append(np.full(len(a), j, np.int64))
        for k in [k for k in cache if k < i]:
            del cache[k]
    xi = np.concatenate(xs_i) if xs_i else np.zeros((0, 3), np.float32)
    xj = np.concatenate(xs_j) if xs_j else np.zeros((0, 3), np.float32)
    pi = np.concatenate(ps_i) if ps_i else np.zeros(0, np.int64)
    pj = np.concatenate(ps_j) if ps_j else np.zeros(0, np.int64)
    gain = np.ones((n, 3))
    bias = np.zeros((n, 3))
    rms0, rms1 = [], []
    matrix, vig = None, None
    if general:
        r2i = np.concatenate(r2s_i) if r2s_i else np.zeros(0)
        r2j = np.concatenate(r2s_j) if r2s_j else np.zeros(0)
        A, bias, k, r1 = _calibrate_general(xi.astype(np.float64), xj.astype(np.float64), pi, pj, r2i, r2j,
                                            segs, n, config)
        gain = np.ascontiguousarray(np.diagonal(A, axis1=1, axis2=2))
        matrix = A if config.model == "affine" else None
        vig = k if config.vignetting else None
        rms0 = [float(np.sqrt(np.mean((xi[:, ch] - xj[:, ch]) ** 2))) if len(xi) else 0.0 for ch in range(3)]
        rms1 = [float(x) for x in r1]
    for ch in range(3 if not general else 0):
        a, c, r0, r1 = _solve_channel(xi[:, ch].astype(np.float64), xj[:, ch].astype(np.float64), pi, pj, n, config)
        g, b = 1.0 / a, -c / a
        # Exact re-anchoring: radiance' = s * radiance + t with s = mean(g), t = mean(b).
        s, t = float(g.mean()), float(b.mean())
        gain[:, ch] = g / s
        bias[:, ch] = b - g * t / s
        rms0.append(r0)
        rms1.append(r1 * s)  # residuals in observed levels (approximately)
    covered = np.zeros(n, bool)
    covered[np.unique(np.concatenate([pi, pj]))] = True
    stats = {"pairs": len(pairs), "samples": int(len(xi)), "frames_without_samples": int((~covered).sum()),
             "rms_before": [round(x, 3) for x in rms0], "rms_after": [round(x, 3) for x in rms1],
             "seconds": round(time.perf_counter() - t0, 2),
             "config": {k: getattr(config, k) for k in config.__dataclass_fields__}}
    if config.model == "gain":
        bias[:] = 0.0
    return PhotometricCalib(tuple(scene.frame_ids), gain, bias, config.model, stats, matrix, vig)
