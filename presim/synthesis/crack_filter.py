"""Crack filling of warped images: switching median (thesis eq. 3.9) and the plain median it replaces.

A forward splat of one pixel per point leaves cracks (empty pixels inside a surface) wherever the
target samples the surface more densely than the source. The *switching* median fills only empty
pixels whose N x N window is more than half non-empty, with the lower median of the non-empty
neighbours' depth and of each color channel; non-empty pixels are never touched, and an empty pixel
along a straight edge (3 of 9 non-empty) stays empty, so edges and small textures survive. The
*plain* median (``mode="median"``) filters every pixel over its whole window, zeros included — the
traditional filter the thesis compares against. Exact definitions: :mod:`kernels_reference`.

Inputs are stacks (L, H, W) so all layers of a view are filtered in one parallel call.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from presim.synthesis.threads import parallel_kernel

__all__ = ["CRACK_FILTERS", "crack_filter"]

CRACK_FILTERS = ("switching_median", "median", "none")


@nb.njit(cache=True, inline="always", error_model="numpy")
def _insertion_sort(a, n):  # pragma: no cover
    for i in range(1, n):
        key = a[i]
        j = i - 1
        while j >= 0 and a[j] > key:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = key


@nb.njit(cache=True, inline="always", error_model="numpy")
def gather_window(d, c, l, y0, y1, x0, x1, bd, b0, b1, b2):  # pragma: no cover
    """Copy the non-empty (depth > 0) pixels of layer ``l`` in rows [y0, y1) x cols [x0, x1) into
    the buffers (depth, 3 color channels); returns their number."""
    n = 0
    for y in range(y0, y1):
        for x in range(x0, x1):
            dd = d[l, y, x]
            if dd > 0:
                bd[n] = dd
                b0[n] = c[l, y, x, 0]
                b1[n] = c[l, y, x, 1]
                b2[n] = c[l, y, x, 2]
                n += 1
    return n


@nb.njit(cache=True, inline="always", error_model="numpy")
def sort_window(bd, b0, b1, b2, n):  # pragma: no cover
    """Sort the first n entries of depth and of each color channel on their own (per-channel
    median, as eq. 3.9); returns the lower median's index."""
    _insertion_sort(bd, n)
    _insertion_sort(b0, n)
    _insertion_sort(b1, n)
    _insertion_sort(b2, n)
    return (n - 1) // 2


@parallel_kernel(cache=True, error_model="numpy")
def _switching_median_kernel(din, cin, dout, cout, r):  # pragma: no cover
    # dout / cout arrive as copies of din / cin; only filled cracks are written.
    # Occupancy counts per window come from column sums + a running sum along the row (O(1) per
    # pixel), so the median gathering runs only for the (few) pixels that get filled.
    L, H, W = din.shape
    n_win = (2 * r + 1) * (2 * r + 1)
    for row in nb.prange(L * H):
        l = row // H
        v = row - l * H
        y0 = max(v - r, 0)
        y1 = min(v + r + 1, H)
        colcnt = np.zeros(W + 2 * r, np.int32)  # padded by r on both sides
        for y in range(y0, y1):
            for u in range(W):
                colcnt[u + r] += np.int32(din[l, y, u] > 0)  # branchless: occupancy is random
        bd = np.empty(n_win, np.float32)
        b0 = np.empty(n_win, np.uint8)
        b1 = np.empty(n_win, np.uint8)
        b2 = np.empty(n_win, np.uint8)
        cnt = 0
        for k in range(2 * r + 1):
            cnt += colcnt[k]
        for u in range(W):
            if u > 0:
                cnt += colcnt[u + 2 * r] - colcnt[u - 1]
            if 2 * cnt <= n_win or din[l, v, u] > 0:
                continue
            n = gather_window(din, cin, l, y0, y1, max(u - r, 0), min(u + r + 1, W), bd, b0, b1, b2)
            k = sort_window(bd, b0, b1, b2, n)
            dout[l, v, u] = bd[k]
            cout[l, v, u, 0] = b0[k]
            cout[l, v, u, 1] = b1[k]
            cout[l, v, u, 2] = b2[k]


@parallel_kernel(cache=True, error_model="numpy")
def _plain_median_kernel(din, cin, dout, cout, r):  # pragma: no cover
    L, H, W = din.shape
    n_win = (2 * r + 1) * (2 * r + 1)
    mid = (n_win - 1) // 2
    for row in nb.prange(L * H):
        l = row // H
        v = row - l * H
        bd = np.empty(n_win, np.float32)
        b0 = np.empty(n_win, np.uint8)
        b1 = np.empty(n_win, np.uint8)
        b2 = np.empty(n_win, np.uint8)
        for u in range(W):
            n = 0
            for y in range(v - r, v + r + 1):
                for x in range(u - r, u + r + 1):
                    if 0 <= y < H and 0 <= x < W:
                        bd[n] = din[l, y, x]
                        b0[n] = cin[l, y, x, 0]
                        b1[n] = cin[l, y, x, 1]
                        b2[n] = cin[l, y, x, 2]
                    else:  # zero padding
                        bd[n] = 0.0
                        b0[n] = 0
                        b1[n] = 0
                        b2[n] = 0
                    n += 1
            _insertion_sort(bd, n)
            dout[l, v, u] = bd[mid]
            if bd[mid] > 0:
                _insertion_sort(b0, n)
                _insertion_sort(b1, n)
                _insertion_sort(b2, n)
                cout[l, v, u, 0] = b0[mid]
                cout[l, v, u, 1] = b1[mid]
                cout[l, v, u, 2] = b2[mid]
            else:
                cout[l, v, u, 0] = 0
                cout[l, v, u, 1] = 0
                cout[l, v, u, 2] = 0


def crack_filter(depth_m: np.ndarray, color: np.ndarray, mode: str = "switching_median",
                 kernel_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Fill cracks of warped images (numba, parallel over rows of all layers).

    Args:
        depth_m: float32 (L, H, W) or (H, W), 0 = empty.
        color: uint8 (L, H, W, 3) or (H, W, 3).
        mode: ``"switching_median"`` (thesis), ``"median"`` (plain) or ``"none"``.
        kernel_px: odd window size N.
    Returns:
        New ``(depth_m, color)`` of the input shapes (the inputs are returned as-is for ``"none"``).
    """
    if mode not in CRACK_FILTERS:
        raise ValueError(f"crack filter must be one of {CRACK_FILTERS}, got {mode!r}")
    if kernel_px < 1 or kernel_px % 2 == 0:
        raise ValueError(f"kernel_px must be odd and >= 1, got {kernel_px}")
    if mode == "none":
        return depth_m, color
    squeeze = depth_m.ndim == 2
    d = depth_m[None] if squeeze else depth_m
    c = color[None] if squeeze else color
    if d.dtype != np.float32 or c.dtype != np.uint8 or c.shape != d.shape + (3,):
        raise ValueError(f"need float32 depth (L,H,W) and uint8 color (L,H,W,3), got {d.dtype} {d.shape}, "
                         f"{c.dtype} {c.shape}")
    d = np.ascontiguousarray(d)
    c = np.ascontiguousarray(c)
    if mode == "switching_median":
        dout, cout = d.copy(), c.copy()
        _switching_median_kernel(d, c, dout, cout, kernel_px // 2)
    else:
        dout, cout = np.empty_like(d), np.empty_like(c)
        _plain_median_kernel(d, c, dout, cout, kernel_px // 2)
    return (dout[0], cout[0]) if squeeze else (dout, cout)
