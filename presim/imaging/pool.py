"""Depth-aware 2x2 pooling of a depth image and its colour: per block, the mean of the valid pixels within a
relative ``depth_tol`` of the block's nearest depth (the rest ignored, so no pooled pixel floats between two
surfaces). Reference :func:`pool_depth_aware_ref`; fast path :func:`pool_depth_aware` (numba, equal)."""

from __future__ import annotations

import numba as nb
import numpy as np

from presim.numba_threads import parallel_kernel

__all__ = ["pool_depth_aware_ref", "pool_depth_aware"]


def pool_depth_aware_ref(depth_m: np.ndarray, color: np.ndarray, depth_tol: float = 0.02
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Reference (numpy, per block) of :func:`pool_depth_aware`. Odd last rows/columns are dropped."""
    H2, W2 = depth_m.shape[0] // 2, depth_m.shape[1] // 2
    d_out = np.zeros((H2, W2), np.float32)
    c_out = np.zeros((H2, W2, 3), np.uint8)
    for i in range(H2):
        for j in range(W2):
            d = depth_m[2 * i:2 * i + 2, 2 * j:2 * j + 2].reshape(-1).astype(np.float64)
            c = color[2 * i:2 * i + 2, 2 * j:2 * j + 2].reshape(-1, 3).astype(np.float64)
            ok = np.isfinite(d) & (d > 0)
            if not ok.any():
                continue
            dmin = d[ok].min()
            sel = ok & (d <= dmin * (1.0 + depth_tol))
            d_out[i, j] = np.float32(d[sel].sum() / sel.sum())
            c_out[i, j] = np.floor(c[sel].sum(0) / sel.sum() + 0.5).astype(np.uint8)
    return d_out, c_out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _pool_row(d, c, tol, dout, cout, i):  # pragma: no cover
    # Row i of the pooled level. Depth summed in float64 in the reference's order; colour in integers:
    # floor(sum / n + 0.5) == (2 sum + n) // (2 n) exactly for n = 1..4 (n = 3: >= 1/6 from an integer).
    W2 = dout.shape[1]
    da = d[2 * i]
    db = d[2 * i + 1]
    ca = c[2 * i]
    cb = c[2 * i + 1]
    one_tol = 1.0 + tol
    for j in range(W2):
        z0 = da[2 * j]
        z1 = da[2 * j + 1]
        z2 = db[2 * j]
        z3 = db[2 * j + 1]
        dmin = np.inf
        if z0 > 0 and z0 < dmin:
            dmin = z0
        if z1 > 0 and z1 < dmin:
            dmin = z1
        if z2 > 0 and z2 < dmin:
            dmin = z2
        if z3 > 0 and z3 < dmin:
            dmin = z3
        if not (dmin < np.inf):
            dout[i, j] = 0.0
            cout[i, j, 0] = 0
            cout[i, j, 1] = 0
            cout[i, j, 2] = 0
            continue
        lim = np.float64(dmin) * one_tol
        if z0 <= lim and z1 <= lim and z2 <= lim and z3 <= lim and z0 > 0 and z1 > 0 and z2 > 0 and z3 > 0:
            # all four pixels (most blocks on a surface)
            sd = ((np.float64(z0) + np.float64(z1)) + np.float64(z2)) + np.float64(z3)
            dout[i, j] = np.float32(sd * 0.25)
            for k in range(3):
                s = (np.int64(ca[2 * j, k]) + np.int64(ca[2 * j + 1, k]) + np.int64(cb[2 * j, k])
                     + np.int64(cb[2 * j + 1, k]))
                cout[i, j, k] = np.uint8((s + 2) >> 2)
            continue
        n = 0
        sd = 0.0
        s0 = 0
        s1 = 0
        s2 = 0
        for a in range(2):
            for b in range(2):
                z = d[2 * i + a, 2 * j + b]
                if z > 0 and z <= lim:
                    n += 1
                    sd += np.float64(z)
                    s0 += np.int64(c[2 * i + a, 2 * j + b, 0])
                    s1 += np.int64(c[2 * i + a, 2 * j + b, 1])
                    s2 += np.int64(c[2 * i + a, 2 * j + b, 2])
        if n == 3:
            dout[i, j] = np.float32(sd / 3.0)
        else:  # n = 1, 2: x * (1 / n) = x / n exactly (a power of two)
            dout[i, j] = np.float32(sd * (1.0 if n == 1 else 0.5))
        cout[i, j, 0] = np.uint8((2 * s0 + n) // (2 * n))
        cout[i, j, 1] = np.uint8((2 * s1 + n) // (2 * n))
        cout[i, j, 2] = np.uint8((2 * s2 + n) // (2 * n))


@parallel_kernel(cache=True, error_model="numpy")
def _pool_kernel(d, c, tol, dout, cout):  # pragma: no cover
    for i in nb.prange(dout.shape[0]):
        _pool_row(d, c, tol, dout, cout, i)


def pool_depth_aware(depth_m: np.ndarray, color: np.ndarray, depth_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """2x2 depth-aware pooling: per block, the mean depth and colour of the valid pixels within ``depth_tol``
    of its nearest depth, 0 without one. float32 depth (0 / non-finite = invalid), uint8 colour -> halved."""
    # Non-finite depths count as invalid without a pass: NaN/-inf fail z > 0, +inf is never within the band.
    d = np.ascontiguousarray(depth_m, np.float32)
    H2, W2 = d.shape[0] // 2, d.shape[1] // 2
    dout = np.empty((H2, W2), np.float32)
    cout = np.empty((H2, W2, 3), np.uint8)
    _pool_kernel(d, np.ascontiguousarray(color, np.uint8), float(depth_tol), dout, cout)
    return dout, cout
