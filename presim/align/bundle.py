"""RGB-D bundle adjustment: camera poses and 3D points from feature observations with depth.

Residuals per observation (camera c sees point p at pixel uv with measured z-depth z):
- reprojection ``(project(T_cam_world_c @ X_p) - uv) / sigma_px`` (2 values);
- depth ``(z_pred - z) / sigma_z(z)`` with ``sigma_z = depth_sigma_coeff * z**2`` (structured-light
  noise grows with the square of the distance), when the observation has depth.
Every residual is passed through a Huber loss (``huber`` in sigma units, by iteratively reweighted
least squares). Solved with scipy's ``least_squares`` (trust region reflective, sparse Jacobian by grouped finite differences: each
residual touches one camera and one point, so 9 column groups cover the whole Jacobian).

Parameters are increments on the initial values: ``R_c = Exp(w_c) R0_c``, ``t_c = t0_c + v_c``,
``X_p = X0_p + dX_p``; fixed cameras (the gauge) have none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

__all__ = ["BAConfig", "BAProblem", "BAResult", "bundle_adjust", "observation_costs", "pose_covariances",
           "pose_information", "residuals_px"]


@dataclass(frozen=True)
class BAConfig:
    sigma_px: float = 1.0
    """Feature position noise, pixels."""
    depth_sigma_coeff: float = 0.0015
    """sigma_z = coeff * z^2 metres (Kinect-class structured light: ~1.4e-3 z^2)."""
    use_depth: bool = False
    """Add the depth residuals (RGB-D, beyond the thesis). Off by default for ``presim align``:
    measured (docs/alignment.md, ablations) reprojection only renders APC +0.47 dB better and lands
    TUM 0.06 cm closer to mocap, and keeps the sample scene's exact poses. The import of captures
    without poses keeps them on (its measured configuration)."""
    huber: float = 2.0
    """Huber threshold in sigma units (residuals beyond it count linearly)."""
    passes: int = 2
    """Solve, drop outliers, solve again (``passes`` solves in all)."""
    outlier_px: float = 4.0
    """Observations with a reprojection error above this after a pass are dropped."""
    outlier_depth_sigma: float = 5.0
    """... or a depth residual above this many sigma."""
    max_nfev: int = 30
    """Function evaluations per reweighting round (each Jacobian costs ~10 more)."""
    irls_rounds: int = 3
    """Huber reweighting rounds per pass."""


@dataclass(frozen=True)
class BAProblem:
    T_cam_world: np.ndarray
    """(C, 4, 4) initial world-to-camera poses."""
    fixed: np.ndarray
    """(C,) bool: cameras held fixed (at least one: the gauge)."""
    K: np.ndarray
    """(C, 4) fx, fy, cx, cy per camera."""
    points_world: np.ndarray
    """(P, 3) initial 3D points."""
    cam_idx: np.ndarray
    """(O,) camera of each observation."""
    pt_idx: np.ndarray
    """(O,) point of each observation."""
    uv: np.ndarray
    """(O, 2) observed pixel."""
    depth_m: np.ndarray
    """(O,) observed z-depth, 0 = none."""


@dataclass(frozen=True)
class BAResult:
    T_cam_world: np.ndarray
    points_world: np.ndarray
    inlier: np.ndarray
    """(O,) bool: observations kept by the last pass."""
    reproj_px_before: np.ndarray
    """(O,) reprojection error at the initial values."""
    reproj_px_after: np.ndarray
    depth_res_m_before: np.ndarray
    """(O,) |z_pred - z| at the initial values (NaN where no depth)."""
    depth_res_m_after: np.ndarray
    nfev: int


def _project(R: np.ndarray, t: np.ndarray, K: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = np.einsum("oij,oj->oi", R, X) + t
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < 1e-6, 1e-6, z)
    u = K[:, 0] * Xc[:, 0] / zs + K[:, 2]
    v = K[:, 1] * Xc[:, 1] / zs + K[:, 3]
    return np.stack([u, v], axis=1), z


def residuals_px(T_cam_world: np.ndarray, K: np.ndarray, points_world: np.ndarray, cam_idx: np.ndarray,
                 pt_idx: np.ndarray, uv: np.ndarray, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(reprojection error px (O,), |depth residual| m (O,), NaN without depth) at given values."""
    R = T_cam_world[cam_idx, :3, :3]
    t = T_cam_world[cam_idx, :3, 3]
    pred, z = _project(R, t, K[cam_idx], points_world[pt_idx])
    err = np.linalg.norm(pred - uv, axis=1)
    dres = np.where(depth_m > 0, np.abs(z - depth_m), np.nan)
    return err, dres


def bundle_adjust(problem: BAProblem, config: BAConfig = BAConfig()) -> BAResult:
    """Refine the free cameras and all points of ``problem`` (see module doc)."""
    p = problem
    C, P, O = len(p.T_cam_world), len(p.points_world), len(p.cam_idx)
    if not np.any(p.fixed):
        raise ValueError("bundle_adjust needs at least one fixed camera (the gauge)")
    if O == 0:
        raise ValueError("bundle_adjust: no observations")
    R0 = p.T_cam_world[:, :3, :3]
    t0 = p.T_cam_world[:, :3, 3]
    free = np.flatnonzero(~p.fixed)
    slot = -np.ones(C, dtype=int)
    slot[free] = np.arange(len(free))
    n_cam = 6 * len(free)
    Kc = p.K[p.cam_idx]

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        R, t = R0.copy(), t0.copy()
        if len(free):
            d = x[:n_cam].reshape(-1, 6)
            R[free] = Rotation.from_rotvec(d[:, :3]).as_matrix() @ R0[free]
            t[free] = t0[free] + d[:, 3:]
        X = p.points_world + x[n_cam:].reshape(P, 3)
        return R, t, X

    def build(active: np.ndarray):
        ci, pi, uv, dm = p.cam_idx[active], p.pt_idx[active], p.uv[active], p.depth_m[active]
        has_d = (dm > 0) if config.use_depth else np.zeros(len(dm), bool)
        sig_z = config.depth_sigma_coeff * dm[has_d] ** 2

        def fun(x: np.ndarray) -> np.ndarray:
            R, t, X = unpack(x)
            pred, z = _project(R[ci], t[ci], Kc[active], X[pi])
            r_px = ((pred - uv) / config.sigma_px).ravel()
            r_d = (z[has_d] - dm[has_d]) / sig_z
            return np.concatenate([r_px, r_d])

        # Sparsity: rows 2o, 2o+1 (reprojection) and the depth row of o touch camera ci[o], point pi[o].
        rows_obs = np.concatenate([2 * np.arange(len(ci)), 2 * np.arange(len(ci)) + 1,
                                   2 * len(ci) + np.arange(int(has_d.sum()))])
        obs_of_row = np.concatenate([np.arange(len(ci)), np.arange(len(ci)), np.flatnonzero(has_d)])
        r_list, c_list = [], []
        cam_slot = slot[ci[obs_of_row]]
        m = cam_slot >= 0
        for k in range(6):
            r_list.append(rows_obs[m])
            c_list.append(6 * cam_slot[m] + k)
        for k in range(3):
            r_list.append(rows_obs)
            c_list.append(n_cam + 3 * pi[obs_of_row] + k)
        rr, cc = np.concatenate(r_list), np.concatenate(c_list)
        sparsity = coo_matrix((np.ones(len(rr)), (rr, cc)), shape=(len(rows_obs), n_cam + 3 * P)).tocsr()
        return fun, sparsity

    x = np.zeros(n_cam + 3 * P)
    active = np.ones(O, dtype=bool)
    nfev = 0
    err0, d0 = residuals_px(p.T_cam_world, p.K, p.points_world, p.cam_idx, p.pt_idx, p.uv, p.depth_m)
    for k in range(max(1, config.passes)):
        fun, sparsity = build(active)
        # Huber by iteratively reweighted least squares: scipy's own robust losses converged slowly
        # here (4 cm off after 100 evaluations on a 5-camera toy problem that the plain loss solves
        # exactly in 6), so each round solves a weighted plain problem, weights w = min(1, k/|r|).
        for _ in range(max(1, config.irls_rounds)):
            r = fun(x)
            a = np.abs(r)
            w = np.sqrt(np.where(a <= config.huber, 1.0, config.huber / np.maximum(a, 1e-12)))
            sol = least_squares(lambda xx, w=w: w * fun(xx), x, jac_sparsity=sparsity, method="trf",
                                x_scale=1.0, max_nfev=config.max_nfev, tr_solver="lsmr", verbose=0)
            x, nfev = sol.x, nfev + sol.nfev
        if k + 1 < config.passes:
            R, t, X = unpack(x)
            T = _compose(R, t)
            err, dres = residuals_px(T, p.K, X, p.cam_idx, p.pt_idx, p.uv, p.depth_m)
            bad = err > config.outlier_px
            if config.use_depth:
                sig = config.depth_sigma_coeff * np.maximum(p.depth_m, 1e-3) ** 2
                bad |= np.nan_to_num(dres / sig, nan=0.0) > config.outlier_depth_sigma
            new_active = ~bad
            if not new_active.any() or np.array_equal(new_active, active):
                break
            active = new_active
    R, t, X = unpack(x)
    T = _compose(R, t)
    err1, d1 = residuals_px(T, p.K, X, p.cam_idx, p.pt_idx, p.uv, p.depth_m)
    return BAResult(T, X, active, err0, err1, d0, d1, nfev)


def _compose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    return T


@dataclass(frozen=True)
class PairObservations:
    """Feature matches between frames with the first frame's depth (the thesis' form of eq. 5.1:
    the 3D point is the key feature lifted with its measured depth, moving with the key's pose)."""

    a_idx: np.ndarray
    """(O,) camera whose depth lifts the feature."""
    b_idx: np.ndarray
    """(O,) camera that observes it."""
    X_a: np.ndarray
    """(O, 3) the feature in camera a's frame (pixel lifted with a's depth)."""
    uv_b: np.ndarray
    """(O, 2) the matched pixel in b."""
    z_b: np.ndarray
    """(O,) b's depth at the matched pixel, 0 = none."""


@dataclass(frozen=True)
class PoseAdjustResult:
    T_world_cam: np.ndarray
    inlier: np.ndarray
    """(O,) bool: observations kept by the last pass."""
    transfer_px_before: np.ndarray
    transfer_px_after: np.ndarray
    nfev: int


def transfer(T_world_cam: np.ndarray, K: np.ndarray, obs: PairObservations) -> tuple[np.ndarray, np.ndarray]:
    """(predicted pixel in b (O, 2), predicted z in b (O,)) of each observation under the poses."""
    Ra, ta = T_world_cam[obs.a_idx, :3, :3], T_world_cam[obs.a_idx, :3, 3]
    Rb, tb = T_world_cam[obs.b_idx, :3, :3], T_world_cam[obs.b_idx, :3, 3]
    Xw = np.einsum("oij,oj->oi", Ra, obs.X_a) + ta
    Rb_t = np.swapaxes(Rb, 1, 2)
    return _project(Rb_t, -np.einsum("oij,oj->oi", Rb_t, tb), K[obs.b_idx], Xw)


def _skew(v: np.ndarray) -> np.ndarray:
    """(O, 3) -> (O, 3, 3) cross-product matrices."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _linearize(T: np.ndarray, K: np.ndarray, obs: PairObservations, sig_z: np.ndarray, use_depth: bool,
               sigma_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals (O, 3) [u, v, z] and their Jacobians (O, 3, 6) w.r.t. increments
    (w, v) of camera a and of camera b (R <- Exp(w) R, t <- t + v), at the poses ``T``."""
    Ra, ta = T[obs.a_idx, :3, :3], T[obs.a_idx, :3, 3]
    Rb, tb = T[obs.b_idx, :3, :3], T[obs.b_idx, :3, 3]
    RaX = np.einsum("oij,oj->oi", Ra, obs.X_a)
    pw = RaX + ta
    y = pw - tb
    RbT = np.swapaxes(Rb, 1, 2)
    pb = np.einsum("oij,oj->oi", RbT, y)
    z = np.where(np.abs(pb[:, 2]) < 1e-6, 1e-6, pb[:, 2])
    fx, fy, cx, cy = (K[obs.b_idx, k] for k in range(4))
    r = np.empty((len(z), 3))
    r[:, 0] = (fx * pb[:, 0] / z + cx - obs.uv_b[:, 0]) / sigma_px
    r[:, 1] = (fy * pb[:, 1] / z + cy - obs.uv_b[:, 1]) / sigma_px
    has_d = (obs.z_b > 0) & use_depth
    r[:, 2] = np.where(has_d, (pb[:, 2] - obs.z_b) / sig_z, 0.0)
    # d(residual)/d(pb)
    P = np.zeros((len(z), 3, 3))
    P[:, 0, 0] = fx / z / sigma_px
    P[:, 0, 2] = -fx * pb[:, 0] / z ** 2 / sigma_px
    P[:, 1, 1] = fy / z / sigma_px
    P[:, 1, 2] = -fy * pb[:, 1] / z ** 2 / sigma_px
    P[:, 2, 2] = np.where(has_d, 1.0 / sig_z, 0.0)
    PRbT = P @ RbT
    Ja = np.concatenate([PRbT @ -_skew(RaX), PRbT], axis=2)          # pb = Rb^T (Exp(w)Ra X + ta + v - tb)
    Jb = np.concatenate([PRbT @ _skew(y), -PRbT], axis=2)             # pb = Rb^T Exp(-w) (y - v)
    return r, Ja, Jb


def _depth_sigma(obs: PairObservations, config: BAConfig) -> np.ndarray:
    """sigma_z of each observation's depth residual, metres (from both depths)."""
    return np.maximum(config.depth_sigma_coeff * np.sqrt(obs.X_a[:, 2] ** 4 + obs.z_b ** 4), 1e-6)


def _normal_equations(C: int, free: np.ndarray, o: PairObservations, r: np.ndarray, Ja: np.ndarray,
                      Jb: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton (J^T W J, J^T W r) over the free cameras' 6-vectors (dense, 6F x 6F)."""
    H = np.zeros((C, C, 6, 6))
    g = np.zeros((C, 6))
    JaW, JbW = Ja * w[:, :, None], Jb * w[:, :, None]
    np.add.at(H, (o.a_idx, o.a_idx), np.einsum("oki,okj->oij", JaW, Ja))
    np.add.at(H, (o.b_idx, o.b_idx), np.einsum("oki,okj->oij", JbW, Jb))
    Hab = np.einsum("oki,okj->oij", JaW, Jb)
    np.add.at(H, (o.a_idx, o.b_idx), Hab)
    np.add.at(H, (o.b_idx, o.a_idx), np.swapaxes(Hab, 1, 2))
    np.add.at(g, o.a_idx, np.einsum("oki,ok->oi", JaW, r))
    np.add.at(g, o.b_idx, np.einsum("oki,ok->oi", JbW, r))
    Hf = H[np.ix_(free, free)].transpose(0, 2, 1, 3).reshape(6 * len(free), 6 * len(free))
    return Hf, g[free].reshape(-1)


def _huber_rho(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 0.5 * a ** 2, k * (a - 0.5 * k))


def observation_costs(T_world_cam: np.ndarray, K: np.ndarray, obs: PairObservations,
                      config: BAConfig = BAConfig()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation, under the poses ``T_world_cam``, the Huber costs of its whitened residuals
    (the terms :func:`adjust_poses` minimises): (reprojection (O,), depth (O,), 0 without depth or
    with ``use_depth`` off; inlier (O,) bool by the adjustment's outlier rule)."""
    sig = _depth_sigma(obs, config)
    r, _, _ = _linearize(np.asarray(T_world_cam, np.float64), K, obs, sig, config.use_depth, config.sigma_px)
    rho_px = _huber_rho(r[:, :2], config.huber).sum(axis=1)
    rho_z = _huber_rho(r[:, 2], config.huber)
    inl = np.hypot(r[:, 0], r[:, 1]) * config.sigma_px <= config.outlier_px
    if config.use_depth:
        inl &= np.abs(r[:, 2]) <= config.outlier_depth_sigma
    return rho_px, rho_z, inl


def _weighted_system(T: np.ndarray, K: np.ndarray, obs: PairObservations, config: BAConfig,
                     free: np.ndarray) -> tuple[np.ndarray, float]:
    """(J^T W J over the ``free`` cameras, s^2 = weighted residual variance per degree of freedom)."""
    r, Ja, Jb = _linearize(T, K, obs, _depth_sigma(obs, config), config.use_depth, config.sigma_px)
    a = np.abs(r)
    w = np.where(a <= config.huber, 1.0, config.huber / np.maximum(a, 1e-12))
    Hf, _ = _normal_equations(len(T), free, obs, r, Ja, Jb, w)
    n_res = 2 * len(r) + (int(np.count_nonzero(r[:, 2])) if config.use_depth else 0)
    dof = max(n_res - 6 * len(free), 1)
    return Hf, float(np.sum(w * r ** 2)) / dof


def pose_information(T_world_cam: np.ndarray, K: np.ndarray, obs: PairObservations,
                     config: BAConfig = BAConfig()) -> np.ndarray:
    """(C, 6, 6) information of each camera's own increment (w rad, v m) with all other cameras held:
    its diagonal block of ``J^T W J / s^2`` (``s^2`` as :func:`pose_covariances`). Its inverse is the
    frame's conditional covariance: how well its own observations fix it, gauge-free."""
    T = np.asarray(T_world_cam, np.float64)
    C = len(T)
    if len(obs.a_idx) == 0:
        return np.zeros((C, 6, 6))
    Hf, s2 = _weighted_system(T, K, obs, config, np.arange(C))
    return Hf.reshape(C, 6, C, 6)[np.arange(C), :, np.arange(C), :] / max(s2, 1e-12)


def pose_covariances(T_world_cam: np.ndarray, fixed: np.ndarray, K: np.ndarray, obs: PairObservations,
                     config: BAConfig = BAConfig()) -> np.ndarray:
    """(C, 6, 6) marginal covariances of the free cameras' increments (w rad, v m) at the poses
    ``T_world_cam`` (NaN for fixed cameras): ``s^2 (J^T W J)^-1`` with the Huber weights, ``s^2`` the
    weighted residual variance per degree of freedom (the measured noise level, not the assumed
    sigma). Relative to the fixed cameras (the gauge); ``obs`` should be the inliers."""
    T = np.asarray(T_world_cam, np.float64)
    fixed = np.asarray(fixed, bool)
    C = len(T)
    free = np.flatnonzero(~fixed)
    cov = np.full((C, 6, 6), np.nan)
    if len(free) == 0 or len(obs.a_idx) == 0:
        return cov
    Hf, s2 = _weighted_system(T, K, obs, config, free)
    try:
        inv = np.linalg.inv(Hf + 1e-12 * np.eye(len(Hf)))
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(Hf)
    blocks = inv.reshape(len(free), 6, len(free), 6)[np.arange(len(free)), :, np.arange(len(free)), :]
    cov[free] = s2 * blocks
    return cov


def adjust_poses(T_world_cam: np.ndarray, fixed: np.ndarray, K: np.ndarray, obs: PairObservations,
                 config: BAConfig = BAConfig()) -> PoseAdjustResult:
    """Pose-only RGB-D adjustment: moves the free cameras so that every feature of a, lifted with a's
    depth, lands on its match in b (reprojection residual) at b's depth (depth residual, sigma from
    both depths). Huber loss by reweighting inside a Levenberg-Marquardt loop with an analytic
    Jacobian (6 parameters per free camera, dense normal equations: hundreds of frames in seconds);
    outlier passes as :func:`bundle_adjust`."""
    T = np.asarray(T_world_cam, dtype=np.float64).copy()
    fixed = np.asarray(fixed, dtype=bool)
    C, O = len(T), len(obs.a_idx)
    if not np.any(fixed):
        raise ValueError("adjust_poses needs at least one fixed camera (the gauge)")
    if O == 0:
        raise ValueError("adjust_poses: no observations")
    free = np.flatnonzero(~fixed)
    sig_all = _depth_sigma(obs, config)
    pred0, _ = transfer(T, K, obs)
    err0 = np.linalg.norm(pred0 - obs.uv_b, axis=1)
    active = np.ones(O, dtype=bool)
    k_h = config.huber
    nfev = 0

    def sub(m: np.ndarray) -> PairObservations:
        return PairObservations(obs.a_idx[m], obs.b_idx[m], obs.X_a[m], obs.uv_b[m], obs.z_b[m])

    def cost(r: np.ndarray) -> float:
        a = np.abs(r)
        return float(np.sum(np.where(a <= k_h, 0.5 * a ** 2, k_h * (a - 0.5 * k_h))))

    def update(Tc: np.ndarray, delta: np.ndarray) -> np.ndarray:
        Tn = Tc.copy()
        d = delta.reshape(-1, 6)
        Tn[free, :3, :3] = Rotation.from_rotvec(d[:, :3]).as_matrix() @ Tc[free, :3, :3]
        Tn[free, :3, 3] = Tc[free, :3, 3] + d[:, 3:]
        return Tn

    if len(free):
        col = -np.ones(C, dtype=int)
        col[free] = np.arange(len(free))
        for p in range(max(1, config.passes)):
            o = sub(active)
            sig = sig_all[active]
            lam = 1e-3
            r, Ja, Jb = _linearize(T, K, o, sig, config.use_depth, config.sigma_px)
            nfev += 1
            c0 = cost(r)
            for _ in range(config.max_nfev * max(1, config.irls_rounds)):
                a = np.abs(r)
                w = np.where(a <= k_h, 1.0, k_h / np.maximum(a, 1e-12))        # Huber IRLS weights
                Hf, gf = _normal_equations(C, free, o, r, Ja, Jb, w)
                while True:
                    A = Hf + lam * np.diag(np.diag(Hf) + 1e-9)
                    try:
                        delta = -np.linalg.solve(A, gf)
                    except np.linalg.LinAlgError:
                        delta = -np.linalg.lstsq(A, gf, rcond=None)[0]
                    Tn = update(T, delta)
                    rn, Jan, Jbn = _linearize(Tn, K, o, sig, config.use_depth, config.sigma_px)
                    nfev += 1
                    cn = cost(rn)
                    if cn <= c0 or lam > 1e8:
                        break
                    lam *= 10
                if cn > c0:
                    break
                T, r, Ja, Jb = Tn, rn, Jan, Jbn
                lam = max(lam / 10, 1e-7)
                done = c0 - cn < 1e-10 * max(c0, 1.0) or np.abs(delta).max() < 1e-10
                c0 = cn
                if done:
                    break
            if p + 1 < config.passes:
                pred, zz = transfer(T, K, obs)
                bad = np.linalg.norm(pred - obs.uv_b, axis=1) > config.outlier_px
                if config.use_depth:
                    bad |= (obs.z_b > 0) & (np.abs(zz - obs.z_b) > config.outlier_depth_sigma * sig_all)
                if not (~bad).any() or np.array_equal(~bad, active):
                    break
                active = ~bad
    pred1, _ = transfer(T, K, obs)
    return PoseAdjustResult(T, active, err0, np.linalg.norm(pred1 - obs.uv_b, axis=1), nfev)
