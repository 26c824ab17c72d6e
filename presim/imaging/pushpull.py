"""Pull-push interpolation (Gortler et al. 1996) of the unknown pixels of an image: pull averages the known
values into ever coarser levels (OpenCV area pooling of premultiplied values and weights) until one has no
unknown pixel, push blends each level's estimate back up (bilinear upsampling).

Reference :func:`pushpull_fill` (any channels, OpenCV); fast path :func:`pushpull_rgbd` (colour + depth, numba
full-size steps); torch: :func:`presim.imaging.torch_ops.pushpull_rgbd_torch`."""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np

from presim.numba_threads import LIGHT_SERIAL_BELOW, parallel_kernel

__all__ = ["pushpull_fill", "pushpull_rgbd"]


def _halve(acc: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next pull level: OpenCV area pooling of premultiplied values (h, w, C) and weights."""
    h2, w2 = (acc.shape[0] + 1) // 2, (acc.shape[1] + 1) // 2
    return (cv2.resize(acc, (w2, h2), interpolation=cv2.INTER_AREA).reshape(h2, w2, acc.shape[2]),
            cv2.resize(w, (w2, h2), interpolation=cv2.INTER_AREA))


def _coarse_levels(acc: np.ndarray, w: np.ndarray, fast: bool) -> np.ndarray:
    """Pull-push from a level to the coarsest with no unknown pixel and back: that level's estimate. Each push
    step is ``acc / max(w, 1e-12) * a + up * (1 - a)``, ``a = clip(w, 0, 1)`` (``fast``: in one numba pass)."""
    levels = []
    while not (w > 0).all() and min(w.shape) > 1:
        levels.append((acc, w))
        acc, w = _halve(acc, w)
    est = acc / np.maximum(w, 1e-12)[..., None]
    for acc_l, w_l in reversed(levels):
        h, ww = w_l.shape
        up = cv2.resize(est, (ww, h), interpolation=cv2.INTER_LINEAR).reshape(h, ww, acc.shape[2])
        if fast:
            est = np.empty_like(up)
            _blend_level_kernel(acc_l, w_l, up, est)
        else:
            alpha = np.clip(w_l, 0.0, 1.0)[..., None]
            est = acc_l / np.maximum(w_l, 1e-12)[..., None] * alpha + up * (1.0 - alpha)
    return est


def pushpull_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Pull-push interpolation of ``values`` (H, W) or (H, W, C) where ``known`` (H, W bool) is False.

    Returns float32 of the input shape, known pixels unchanged (zeros when nothing is known)."""
    squeeze = values.ndim == 2
    v = values[..., None] if squeeze else values
    H, W, C = v.shape
    known_u8 = known.view(np.uint8)
    v32 = np.ascontiguousarray(v, dtype=np.float32)
    # Level 0: weights are 0/1, so premultiplying is masking (cv2.copyTo is ~5x numpy indexing).
    acc = cv2.copyTo(v32, known_u8, np.zeros_like(v32)).reshape(H, W, C)
    w = known.astype(np.float32)
    if min(H, W) > 1:
        acc, w = _halve(acc, w)
        est = _coarse_levels(acc, w, False)
    else:
        est = acc / np.maximum(w, 1e-12)[..., None]
    up = cv2.resize(est, (W, H), interpolation=cv2.INTER_LINEAR).reshape(H, W, C)
    out = cv2.copyTo(v32, known_u8, np.ascontiguousarray(up)).reshape(H, W, C)
    return out[..., 0] if squeeze else out


@parallel_kernel(cache=True, serial_below=LIGHT_SERIAL_BELOW["pass"], size_arg=1, error_model="numpy")  # size of depth
def _pull0_kernel(color, depth, known, with_color, acc, w):  # pragma: no cover
    # Level 0 -> 1 for even H and W: 2x2 means (premultiplied values, 0/1 weights), known children added in
    # row order as selects (+0.0 for unknown leaves the sum bit for bit unchanged): no branch on the mask.
    h2, w2 = w.shape
    C = acc.shape[2]
    zero = np.float32(0.0)
    quarter = np.float32(0.25)
    for i in nb.prange(h2):
        ka = known[2 * i]
        kb = known[2 * i + 1]
        da = depth[2 * i]
        db = depth[2 * i + 1]
        ca = color[2 * i] if with_color else color[0]
        cb = color[2 * i + 1] if with_color else color[0]
        for j in range(w2):
            x0 = 2 * j
            x1 = x0 + 1
            k0 = ka[x0]
            k1 = ka[x1]
            k2 = kb[x0]
            k3 = kb[x1]
            sw = (((zero + (np.float32(1.0) if k0 else zero)) + (np.float32(1.0) if k1 else zero))
                  + (np.float32(1.0) if k2 else zero)) + (np.float32(1.0) if k3 else zero)
            sd = (((zero + (da[x0] if k0 else zero)) + (da[x1] if k1 else zero)) + (db[x0] if k2 else zero)) \
                + (db[x1] if k3 else zero)
            if with_color:
                for ch in range(3):
                    s = (((zero + (np.float32(ca[x0, ch]) if k0 else zero)) + (np.float32(ca[x1, ch]) if k1 else zero))
                         + (np.float32(cb[x0, ch]) if k2 else zero)) + (np.float32(cb[x1, ch]) if k3 else zero)
                    acc[i, j, ch] = s * quarter
            acc[i, j, C - 1] = sd * quarter
            w[i, j] = sw * quarter


@nb.njit(cache=True, inline="always", error_model="numpy")
def _taps(i, n_coarse):  # pragma: no cover
    # Bilinear taps of fine index i in the coarser level: coordinate (i + 0.5) / 2 - 0.5, clamped.
    y = min(max((i + 0.5) * 0.5 - 0.5, 0.0), n_coarse - 1.0)
    y0 = int(y)
    return y0, min(y0 + 1, n_coarse - 1), np.float32(y - y0)


@parallel_kernel(cache=True, serial_below=LIGHT_SERIAL_BELOW["pass"], error_model="numpy")
def _push0_kernel(known, with_color, est_c, color_out, depth_out):  # pragma: no cover
    # Level 0: only unknown pixels are written (outputs are copies of the inputs); column taps computed once.
    H, W = known.shape
    hc, wc, C = est_c.shape
    tx0 = np.empty(W, np.int64)
    tx1 = np.empty(W, np.int64)
    tfx = np.empty(W, np.float32)
    for j in range(W):
        tx0[j], tx1[j], tfx[j] = _taps(j, wc)
    for i in nb.prange(H):
        y0, y1, fy = _taps(i, hc)
        for j in range(W):
            if known[i, j]:
                continue
            x0 = tx0[j]
            x1 = tx1[j]
            fx = tfx[j]
            if with_color:
                for ch in range(3):
                    up = ((est_c[y0, x0, ch] * (1 - fx) + est_c[y0, x1, ch] * fx) * (1 - fy)
                          + (est_c[y1, x0, ch] * (1 - fx) + est_c[y1, x1, ch] * fx) * fy)
                    color_out[i, j, ch] = np.uint8(min(max(up + 0.5, 0.0), 255.0))
            ch = C - 1
            depth_out[i, j] = ((est_c[y0, x0, ch] * (1 - fx) + est_c[y0, x1, ch] * fx) * (1 - fy)
                               + (est_c[y1, x0, ch] * (1 - fx) + est_c[y1, x1, ch] * fx) * fy)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _blend_level_kernel(acc, w, up, out):  # pragma: no cover
    # One push step of pushpull_fill: acc / max(w, 1e-12) * a + up * (1 - a), a = clip(w, 0, 1); float32, no FMA.
    h, ww, C = acc.shape
    eps = np.float32(1e-12)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for i in range(h):
        for j in range(ww):
            wv = w[i, j]
            a = min(max(wv, zero), one)
            den = max(wv, eps)
            b = one - a
            for ch in range(C):
                out[i, j, ch] = acc[i, j, ch] / den * a + up[i, j, ch] * b


def pushpull_rgbd(color: np.ndarray | None, depth_m: np.ndarray, valid: np.ndarray
                  ) -> tuple[np.ndarray | None, np.ndarray]:
    """Pull-push of colour (uint8 (H, W, 3) or None) and depth where ``valid`` is False: new ``(color,
    depth_m)``, colour rounded. = :func:`pushpull_fill` up to float rounding for even H, W (numba full-size
    steps, OpenCV coarser levels; tested); odd sizes use it."""
    H, W = valid.shape
    with_color = color is not None
    if H % 2 or W % 2 or min(H, W) < 2:
        vals = depth_m[..., None] if not with_color else np.concatenate(
            [color.astype(np.float32), depth_m[..., None]], axis=-1)
        both = pushpull_fill(vals, valid)
        out_c = np.clip(both[..., :3] + 0.5, 0, 255).astype(np.uint8) if with_color else None
        return out_c, np.ascontiguousarray(both[..., -1])
    known = np.ascontiguousarray(valid, np.bool_)
    depth_m = np.ascontiguousarray(depth_m, np.float32)
    col = np.ascontiguousarray(color, np.uint8) if with_color else np.zeros((1, 1, 3), np.uint8)
    C = 4 if with_color else 1
    acc = np.empty((H // 2, W // 2, C), np.float32)
    w = np.empty(acc.shape[:2], np.float32)
    _pull0_kernel(col, depth_m, known, with_color, acc, w)
    est = _coarse_levels(acc, w, True)  # coarser levels as pushpull_fill
    out_c = col.copy() if with_color else None
    out_d = depth_m.copy()
    _push0_kernel(known, with_color, np.ascontiguousarray(est, np.float32), out_c if with_color else col, out_d)
    return out_c, out_d
