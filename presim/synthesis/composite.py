"""Compositing of layers and views, and the hole analysis that drives the adaptive loop (§3.4.4).

- :func:`composite_layers`: front to back over the layers of one view (a pixel takes the nearest
  layer, in the source view's depth order, that has a value). Because every layer was crack-filled
  on its own first, a crack in a foreground layer is filled with foreground, never with background
  seen through it — the point of layered warping.
- :func:`merge_view`: write a view's image into the accumulated target image only on pixels the
  accumulator marks as replaceable (its holes, grown by the hole dilation); earlier (better ranked)
  views are never overwritten elsewhere.
- :func:`analyse_holes`: connected components of the empty pixels (8-connected, runs + union-find). The area of
  the largest component decides whether another view is warped; components of at least
  ``big_hole_px`` pixels are dilated by ``hole_dilation_px`` so the next view also replaces the rim
  of a big hole, where ghost contours (misaligned color/depth edges) live.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from presim.synthesis.crack_filter import gather_window, sort_window
from presim.synthesis.threads import LIGHT_SERIAL_BELOW, parallel_kernel

__all__ = ["HoleStats", "PACKED_MAX_LAYERS", "composite_layers", "filtered_composite", "filtered_composite_masked",
           "filtered_composite_packed", "filtered_composite_banded", "warp_tiles", "tile_any", "TILED_MIN_PIXELS",
           "TILED_MAX_FRAC", "merge_view", "merge_view_holes", "merge_into_holes", "analyse_holes",
           "analyse_hole_mask"]


@parallel_kernel(cache=True, error_model="numpy")
def _composite_kernel(d, c, dout, cout):  # pragma: no cover
    L, H, W = d.shape
    for v in nb.prange(H):
        for u in range(W):
            dout[v, u] = 0.0
            cout[v, u, 0] = 0
            cout[v, u, 1] = 0
            cout[v, u, 2] = 0
            for l in range(L):
                if d[l, v, u] > 0:
                    dout[v, u] = d[l, v, u]
                    cout[v, u, 0] = c[l, v, u, 0]
                    cout[v, u, 1] = c[l, v, u, 1]
                    cout[v, u, 2] = c[l, v, u, 2]
                    break


def composite_layers(depth_m: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Front-to-back composite of layers (numba).

    Args:
        depth_m: float32 (L, H, W), 0 = empty; color: uint8 (L, H, W, 3).
    Returns:
        ``(depth_m (H, W) float32, color (H, W, 3) uint8)``.
    """
    L, H, W = depth_m.shape
    if L == 1:
        return depth_m[0].copy(), color[0].copy()
    dout = np.empty((H, W), np.float32)
    cout = np.empty((H, W, 3), np.uint8)
    _composite_kernel(depth_m, color, dout, cout)
    return dout, cout


_NO_MASK = np.zeros((1, 1), np.bool_)


def merge_view(acc_depth_m: np.ndarray, acc_color: np.ndarray, acc_source: np.ndarray,
               replace: np.ndarray, depth_m: np.ndarray, color: np.ndarray, view_id: int) -> None:
    """In place: where ``replace`` (bool (H, W)) and the view has a value, take the view's pixel.

    Args:
        acc_depth_m / acc_color / acc_source: the accumulated target image (float32 (H, W),
            uint8 (H, W, 3), int32 (H, W) scene frame index, -1 = none), updated in place.
        depth_m / color: the view's composited image.
        view_id: scene frame index written to ``acc_source``.
    """
    merge_view_holes(acc_depth_m, acc_color, acc_source, replace, depth_m, color, view_id,
                     np.empty(acc_depth_m.shape, np.uint8))


@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _take_pixel(acc_d, acc_c, acc_src, d, c, v, u, view_id):  # pragma: no cover
    # The accumulator's pixel (v, u) := the view's, and its source id.
    acc_d[v, u] = d[v, u]
    acc_c[v, u, 0] = c[v, u, 0]
    acc_c[v, u, 1] = c[v, u, 1]
    acc_c[v, u, 2] = c[v, u, 2]
    acc_src[v, u] = view_id


@parallel_kernel(cache=True, serial_below=LIGHT_SERIAL_BELOW["pass"], error_model="numpy")
def _merge_holes_kernel(acc_d, acc_c, acc_src, replace, d, c, view_id, first, holes):  # pragma: no cover
    # The merge (where replace and the view has a value, take the view's pixel; for the first view
    # only its source ids) + the hole mask of the result (1 where the accumulated depth is not > 0)
    # and its count, in one pass.
    H, W = acc_d.shape
    n = 0
    for v in nb.prange(H):
        for u in range(W):
            if first:
                acc_src[v, u] = view_id if d[v, u] > 0 else np.int32(-1)
            elif replace[v, u] and d[v, u] > 0:
                _take_pixel(acc_d, acc_c, acc_src, d, c, v, u, view_id)
            h = np.uint8(0) if acc_d[v, u] > 0 else np.uint8(1)
            holes[v, u] = h
            n += np.int64(h)
    return n


def merge_view_holes(acc_depth_m: np.ndarray, acc_color: np.ndarray, acc_source: np.ndarray,
                     replace: np.ndarray | None, depth_m: np.ndarray, color: np.ndarray, view_id: int,
                     holes: np.ndarray) -> int:
    """:func:`merge_view` and the hole mask of the merged image in one pass (numba).

    With ``replace`` None (the first view, whose image IS the accumulator: ``acc_depth_m`` is
    ``depth_m``), only ``acc_source`` is written: ``view_id`` where the view has a value, else -1.
    Then ``holes`` (uint8 (H, W)) = 1 where ``acc_depth_m`` is not > 0, else 0 (what
    :func:`analyse_holes` derives from the coverage mask ``acc_depth_m > 0``).

    Returns:
        The number of hole pixels.
    """
    first = replace is None
    return int(_merge_holes_kernel(acc_depth_m, acc_color, acc_source, _NO_MASK if first else replace, depth_m,
                                   color, np.int32(view_id), first, holes))


@parallel_kernel(cache=True, serial_below=LIGHT_SERIAL_BELOW["map"], error_model="numpy")
def _merge_into_holes_kernel(acc_d, acc_c, acc_src, replace, words, d, c, view_id, holes):  # pragma: no cover
    # The merge of a later view, updating the previous hole mask in place: a pixel stops being a
    # hole exactly where the merge writes a depth > 0 (elsewhere the accumulator is unchanged).
    # Returns the number of hole pixels filled. Reads the replace mask 8 pixels at a time as
    # ``words`` (its rows as uint64, :func:`_row_words`; (H, 0): every pixel), the rest only where
    # it is set.
    H, W = acc_d.shape
    nw = words.shape[1]
    filled = 0
    for v in nb.prange(H):
        wrow = words[v]
        for k in range(nw if nw > 0 else 1):
            if nw > 0:
                if wrow[k] == 0:
                    continue
                ua = 8 * k
                ub = min(ua + 8, W)  # the last word of a row may run past W (zero padding)
            else:
                ua = 0
                ub = W
            for u in range(ua, ub):
                if replace[v, u] and d[v, u] > 0:
                    _take_pixel(acc_d, acc_c, acc_src, d, c, v, u, view_id)
                    filled += np.int64(holes[v, u])
                    holes[v, u] = 0
    return filled


def merge_into_holes(acc_depth_m: np.ndarray, acc_color: np.ndarray, acc_source: np.ndarray,
                     replace: np.ndarray, depth_m: np.ndarray, color: np.ndarray, view_id: int,
                     holes: np.ndarray) -> int:
    """:func:`merge_view`, and ``holes`` (uint8 (H, W), the accumulator's hole mask before the merge,
    as :func:`merge_view_holes` or this function left it) updated in place to the merged image's
    (1 where ``acc_depth_m`` is not > 0). Only the replaceable pixels are visited besides the
    mask itself: what a later view of the adaptive loop needs (same result as
    :func:`merge_view_holes`, tested).

    Returns:
        The number of hole pixels the view filled (the new hole count is the old one minus this).
    """
    r8 = replace.view(np.uint8)
    return int(_merge_into_holes_kernel(acc_depth_m, acc_color, acc_source, r8, _row_words(r8), depth_m, color,
                                        np.int32(view_id), holes))


@dataclass(frozen=True)
class HoleStats:
    """Holes (empty pixels) of an image after some views were merged."""

    hole_frac: float
    """Fraction of empty pixels."""
    largest_hole_px: int
    """Area of the largest 8-connected hole, pixels (0 when there is none)."""
    replace: np.ndarray | None
    """bool (H, W): pixels the next view may write (the holes, big ones dilated); None if not asked."""
    big: np.ndarray | None = None
    """bool (H, W): pixels of holes of at least ``big_hole_px`` (None if not asked)."""


@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _root(parent, i):  # pragma: no cover
    # Union-find root of run i, halving the path on the way.
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _hole_runs_kernel(holes, words, n_hole, big_hole_px, big, half, replace):  # pragma: no cover
    # 8-connected components of the nonzero pixels of holes (uint8 (H, W)): the runs of each row,
    # each joined (union-find) with the runs of the row above that overlap it or touch it
    # diagonally ([x0, x1) and [y0, y1) touch when x0 <= y1 and y0 <= x1). Zero 8-pixel groups are
    # skipped with ``words`` (the rows as uint64; (H, 0) to read every pixel). Returns (area of
    # the largest component, whether one has >= big_hole_px pixels); when ``big`` has the shape of
    # holes, writes it: 1 on the components of >= big_hole_px pixels, else 0. When ``replace`` has
    # the shape of holes, writes it too: holes OR big dilated by a structuring element whose row i
    # (of len(half), centred) is the column range [-half[i], half[i]] (empty when half[i] < 0;
    # cv2.dilate of such an element, pixels outside the image contributing nothing). n_hole (the
    # nonzero pixels) bounds the number of runs.
    H, W = holes.shape
    nw = words.shape[1]
    cap = max(n_hole, 1)
    ry = np.empty(cap, np.int32)
    rx0 = np.empty(cap, np.int32)
    rx1 = np.empty(cap, np.int32)
    parent = np.empty(cap, np.int32)
    n = 0
    pa = 0  # runs of the row above: [pa, pb)
    pb = 0
    for y in range(H):
        row = holes[y]
        ra = n
        u = 0
        while u < W:
            if nw > 0 and (u & 7) == 0:  # skip the groups of 8 empty pixels
                k = u >> 3
                while k < nw and words[y, k] == 0:
                    k += 1
                u = k << 3
                if u >= W:
                    break
            if row[u] != 0:
                s = u
                u += 1
                while u < W and row[u] != 0:
                    u += 1
                if n == cap:
                    raise ValueError("analyse_hole_mask: n_hole is smaller than the mask's nonzero pixels")
                ry[n] = y
                rx0[n] = s
                rx1[n] = u
                parent[n] = n
                n += 1
            else:
                u += 1
        j = pa
        for i in range(ra, n):  # both rows' runs are in increasing x: one merge pass
            a0 = rx0[i]
            a1 = rx1[i]
            while j < pb and rx1[j] < a0:
                j += 1
            k = j
            while k < pb and rx0[k] <= a1:
                ri = _root(parent, i)
                rk = _root(parent, k)
                if ri < rk:
                    parent[rk] = ri
                elif rk < ri:
                    parent[ri] = rk
                k += 1
        pa = ra
        pb = n
    area = np.zeros(n, np.int64)
    for i in range(n):
        r = _root(parent, i)
        parent[i] = r
        area[r] += rx1[i] - rx0[i]
    largest = 0
    any_big = False
    for i in range(n):
        largest = max(largest, area[i])
        any_big = any_big or area[i] >= big_hole_px
    if big.shape[0] == H and big.shape[1] == W:
        big[:, :] = 0
        for i in range(n):
            if area[parent[i]] >= big_hole_px:
                big[ry[i], rx0[i]:rx1[i]] = 1
    if replace.shape[0] == H and replace.shape[1] == W:
        for y in range(H):  # explicit loops: ~3x faster here than numba's slice assignments
            for x in range(W):
                replace[y, x] = holes[y, x]
        r = len(half) // 2
        for i in range(n):
            if area[parent[i]] < big_hole_px:
                continue
            for e in range(len(half)):
                h = half[e]
                y = ry[i] + r - e  # cv2 applies the reflected element
                if h < 0 or y < 0 or y >= H:
                    continue
                for x in range(max(rx0[i] - h, 0), min(rx1[i] + h, W)):
                    replace[y, x] = 1
    return largest, any_big


def _row_words(mask: np.ndarray) -> np.ndarray:
    """The rows of a uint8 (H, W) mask as uint64 words, 8 pixels each (pixel 8k + j is byte j of
    word k on a little-endian machine): ``ceil(W / 8)`` words per row. A C-contiguous mask whose W
    is a multiple of 8 is viewed as is; any other is copied into rows padded with zeros to a
    multiple of 8 (a copy of the mask, ~20 us at 638x478, against the pixel-by-pixel scans it
    replaces: ~0.5 ms per hole analysis and per tile marking there). The kernels that read the
    words bound every pixel index by W. (H, 0) when W is 0."""
    H, W = mask.shape
    if W % 8 == 0 and mask.flags.c_contiguous:
        return mask.view(np.uint64) if W else np.zeros((H, 0), np.uint64)
    padded = np.zeros((H, -(-W // 8) * 8), np.uint8)
    padded[:, :W] = mask
    return padded.view(np.uint64)


_ELLIPSES: dict[int, np.ndarray] = {}


def _ellipse(k: int) -> np.ndarray:
    """OpenCV's k x k elliptic structuring element (cached: it is asked for once per view)."""
    se = _ELLIPSES.get(k)
    if se is None:
        se = _ELLIPSES[k] = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    return se


_ELLIPSE_ROWS: dict[int, np.ndarray] = {}
_NO_HALF = np.zeros(0, np.int64)
_NO_U8 = np.zeros((0, 0), np.uint8)


def _ellipse_rows(k: int) -> np.ndarray:
    """int64 (k,): the half width of each row of :func:`_ellipse` (k) about the centre column (-1
    for an empty row): each row of OpenCV's ellipse is one run centred on the centre column."""
    half = _ELLIPSE_ROWS.get(k)
    if half is None:
        r = k // 2
        half = np.full(k, -1, np.int64)
        for i, row in enumerate(_ellipse(k).astype(bool)):
            cols = np.flatnonzero(row)
            if len(cols):
                h = r - cols[0]
                if cols[-1] != r + h or len(cols) != 2 * h + 1:
                    raise AssertionError(f"OpenCV's {k}x{k} ellipse: row {i} is not one centred run")
                half[i] = h
        _ELLIPSE_ROWS[k] = half
    return half


def analyse_holes(valid: np.ndarray, big_hole_px: int = 16, hole_dilation_px: int = 2,
                  want_replace: bool = True, stop_px: float = 0.0, want_largest: bool = True) -> HoleStats:
    """Hole statistics of a coverage mask, and the mask of pixels the next view may replace.

    Args:
        valid: bool (H, W), True where the accumulated image has a value.
        big_hole_px: holes of at least this many pixels are "big" and get dilated.
        hole_dilation_px: dilation radius of big holes (0 = no dilation).
        want_replace: also build the replace mask (skipped when no further view will be warped).
        stop_px: when all holes together have at most this many pixels the largest one does too:
            the components are not computed (``largest_hole_px`` is then that upper bound and
            ``replace`` / ``big`` are None) — the adaptive loop stops there anyway.
        want_largest: False (with ``want_replace`` False): only the hole fraction is wanted (the
            last view of a frame); ``largest_hole_px`` is then the total hole area, an upper bound.

    Components are found as runs of hole pixels along the rows joined by union-find with the runs
    of the row above (numba, :func:`_hole_runs_kernel`; empty groups of 8 pixels skipped when the
    width is a multiple of 8): one pass for the components, their areas and the big-hole mask
    (apc capture, 640x480: 93 against 499 us per mask for OpenCV's labelling + an areas pass + a
    lookup pass; tested against scipy's labelling).
    """
    holes = (~valid).view(np.uint8) if valid.dtype == np.bool_ else (valid == 0).astype(np.uint8)
    return analyse_hole_mask(holes, cv2.countNonZero(holes), big_hole_px, hole_dilation_px, want_replace,
                             stop_px, want_largest)


def analyse_hole_mask(holes: np.ndarray, n_hole: int, big_hole_px: int = 16, hole_dilation_px: int = 2,
                      want_replace: bool = True, stop_px: float = 0.0, want_largest: bool = True) -> HoleStats:
    """:func:`analyse_holes` from the hole mask itself: ``holes`` uint8 (H, W), 1 = empty pixel,
    and its count ``n_hole`` (what :func:`merge_view_holes` returns)."""
    H, W = holes.shape
    if n_hole == 0:
        return HoleStats(0.0, 0, np.zeros((H, W), bool) if want_replace else None)
    if n_hole <= stop_px or not (want_largest or want_replace):
        return HoleStats(n_hole / float(H * W), n_hole, None, None)
    holes = np.ascontiguousarray(holes)
    big = np.empty((H, W) if want_replace else (0, 0), np.uint8)
    # The replace mask (holes, big ones dilated by OpenCV's ellipse) is written by the same kernel
    # call: a cv2.dilate and a cv2.bitwise_or less per view (their cold calls cost ~15-25 µs at
    # 128x128 inside frames).
    half = _ellipse_rows(2 * hole_dilation_px + 1) if hole_dilation_px > 0 else _NO_HALF
    replace = np.empty((H, W), np.uint8) if want_replace else _NO_U8
    largest, _ = _hole_runs_kernel(holes, _row_words(holes), int(n_hole), int(big_hole_px), big, half, replace)
    if not want_replace:
        return HoleStats(n_hole / float(H * W), int(largest), None, None)
    return HoleStats(n_hole / float(H * W), int(largest), replace.view(bool), big.view(bool))


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _layer_value_at(d, c, l, v, u, r, n_win, bd, b0, b1, b2, out_c):  # pragma: no cover
    """Switching-median value of layer l at (v, u): depth (0 if it stays empty); color in out_c."""
    L, H, W = d.shape
    if d[l, v, u] > 0:
        out_c[0] = c[l, v, u, 0]
        out_c[1] = c[l, v, u, 1]
        out_c[2] = c[l, v, u, 2]
        return d[l, v, u]
    n = gather_window(d, c, l, max(v - r, 0), min(v + r + 1, H), max(u - r, 0), min(u + r + 1, W),
                      bd, b0, b1, b2)
    if 2 * n <= n_win:
        return np.float32(0.0)
    k = sort_window(bd, b0, b1, b2, n)
    out_c[0] = b0[k]
    out_c[1] = b1[k]
    out_c[2] = b2[k]
    return bd[k]


@parallel_kernel(cache=True, error_model="numpy")
def _masked_layers_kernel(d, c, mask, r, dout, cout):  # pragma: no cover
    L, H, W = d.shape
    n_win = (2 * r + 1) * (2 * r + 1)
    for v in nb.prange(H):
        bd = np.empty(n_win, np.float32)
        b0 = np.empty(n_win, np.uint8)
        b1 = np.empty(n_win, np.uint8)
        b2 = np.empty(n_win, np.uint8)
        px = np.zeros(3, np.uint8)
        for u in range(W):
            if not mask[v, u]:
                continue
            dout[v, u] = 0.0
            cout[v, u, 0] = 0
            cout[v, u, 1] = 0
            cout[v, u, 2] = 0
            for l in range(L):
                z = _layer_value_at(d, c, l, v, u, r, n_win, bd, b0, b1, b2, px)
                if z > 0:
                    dout[v, u] = z
                    cout[v, u, 0] = px[0]
                    cout[v, u, 1] = px[1]
                    cout[v, u, 2] = px[2]
                    break


@parallel_kernel(cache=True, error_model="numpy")
def _masked_single_kernel(d, c, mask, r, dout, cout):  # pragma: no cover
    H, W = d.shape
    n_win = (2 * r + 1) * (2 * r + 1)
    d3 = d.reshape((1, H, W))
    c3 = c.reshape((1, H, W, 3))
    for v in nb.prange(H):
        bd = np.empty(n_win, np.float32)
        b0 = np.empty(n_win, np.uint8)
        b1 = np.empty(n_win, np.uint8)
        b2 = np.empty(n_win, np.uint8)
        px = np.zeros(3, np.uint8)
        for u in range(W):
            if mask[v, u]:
                z = _layer_value_at(d3, c3, 0, v, u, r, n_win, bd, b0, b1, b2, px)
                dout[v, u] = z
                cout[v, u, 0] = px[0] if z > 0 else 0
                cout[v, u, 1] = px[1] if z > 0 else 0
                cout[v, u, 2] = px[2] if z > 0 else 0


def filtered_composite_masked(depth_m: np.ndarray, color: np.ndarray, replace: np.ndarray,
                              kernel_px: int = 3, seam_pass: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Switching-median + front-to-back composite (+ seam pass) evaluated only where it is needed.

    Equals ``crack_filter`` per layer -> :func:`composite_layers` -> ``crack_filter`` (seam pass) on
    every pixel of ``replace``; other pixels are UNDEFINED. Used for the views after the first, which
    only write into the (usually small) replaceable region. The composite is evaluated on
    ``replace`` grown by the kernel radius, which is all the seam pass reads.

    Args:
        depth_m: float32 (L, H, W) warped layers; color: uint8 (L, H, W, 3).
        replace: bool (H, W) pixels whose final value is wanted.
    Returns:
        ``(depth_m (H, W), color (H, W, 3))``, exact on ``replace``.
    """
    L, H, W = depth_m.shape
    r = kernel_px // 2
    need = replace
    if seam_pass and r > 0:
        k = 2 * r + 1
        need = cv2.dilate(replace.view(np.uint8), np.ones((k, k), np.uint8)).view(bool)
    # Uninitialised outside the mask: every consumer reads masked pixels only (no zeroing cost).
    comp_d = np.empty((H, W), np.float32)
    comp_c = np.empty((H, W, 3), np.uint8)
    _masked_layers_kernel(depth_m, color, need, r, comp_d, comp_c)
    if not seam_pass:
        return comp_d, comp_c
    out_d = np.empty((H, W), np.float32)
    out_c = np.empty((H, W, 3), np.uint8)
    _masked_single_kernel(comp_d, comp_c, replace, r, out_d, out_c)
    return out_d, out_c


@parallel_kernel(cache=True, error_model="numpy")
def _fused_filter_composite_kernel(d, c, r, dout, cout):  # pragma: no cover
    L, H, W = d.shape
    n_win = (2 * r + 1) * (2 * r + 1)
    for v in nb.prange(H):
        y0 = max(v - r, 0)
        y1 = min(v + r + 1, H)
        colcnt = np.zeros((L, W + 2 * r), np.int32)  # per layer, padded by r on both sides
        for l in range(L):
            for y in range(y0, y1):
                for u in range(W):
                    colcnt[l, u + r] += np.int32(d[l, y, u] > 0)
        cnt = np.zeros(L, np.int32)
        for l in range(L):
            for k in range(2 * r + 1):
                cnt[l] += colcnt[l, k]
        bd = np.empty(n_win, np.float32)
        b0 = np.empty(n_win, np.uint8)
        b1 = np.empty(n_win, np.uint8)
        b2 = np.empty(n_win, np.uint8)
        for u in range(W):
            if u > 0:
                for l in range(L):
                    cnt[l] += colcnt[l, u + 2 * r] - colcnt[l, u - 1]
            dout[v, u] = 0.0
            cout[v, u, 0] = 0
            cout[v, u, 1] = 0
            cout[v, u, 2] = 0
            for l in range(L):
                z = d[l, v, u]
                if z > 0:
                    dout[v, u] = z
                    cout[v, u, 0] = c[l, v, u, 0]
                    cout[v, u, 1] = c[l, v, u, 1]
                    cout[v, u, 2] = c[l, v, u, 2]
                    break
                if 2 * cnt[l] > n_win:
                    n = gather_window(d, c, l, y0, y1, max(u - r, 0), min(u + r + 1, W), bd, b0, b1, b2)
                    k = sort_window(bd, b0, b1, b2, n)
                    dout[v, u] = bd[k]
                    cout[v, u, 0] = b0[k]
                    cout[v, u, 1] = b1[k]
                    cout[v, u, 2] = b2[k]
                    break


def filtered_composite(depth_m: np.ndarray, color: np.ndarray, kernel_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Switching median of every layer fused with the front-to-back composite (numba).

    Equals ``composite_layers(*crack_filter(depth_m, color, "switching_median", kernel_px))`` but
    evaluates a layer's median only where no nearer layer already gave the pixel a value, and never
    materializes the filtered layer stack (one pass, no copies).

    Args:
        depth_m: float32 (L, H, W) warped layers, 0 = empty; color: uint8 (L, H, W, 3).
    Returns:
        ``(depth_m (H, W), color (H, W, 3))``.
    """
    L, H, W = depth_m.shape
    dout = np.empty((H, W), np.float32)
    cout = np.empty((H, W, 3), np.uint8)
    _fused_filter_composite_kernel(depth_m, color, kernel_px // 2, dout, cout)
    return dout, cout


# ---- crack mask first: packed occupancy counts (3 x 3 switching median, up to 8 layers) -------
#
# A 3 x 3 switching median fills an empty pixel of layer l when at least 5 of its 9 window pixels are
# non-empty in layer l. Per pixel, one byte holds which layers are non-empty; a lookup table spreads
# the byte into one 4-bit counter per layer (a uint32 for 8 layers), so the 3 x 3 sums of all layers
# are 9 integer additions (column sums reused along the row). ``(P + 3) & 8`` per nibble flags the
# layers whose count is >= 5: only those pixels (the cracks) gather and sort a window; every other
# pixel takes its nearest non-empty layer with no neighbourhood read at all.

PACKED_MAX_LAYERS = 8
"""Layers the packed occupancy path supports (4-bit counters in a uint32)."""

_SPREAD = np.array([sum(((b >> l) & 1) << (4 * l) for l in range(8)) for b in range(256)], np.uint32)
_GE5 = np.uint32(0x33333333)  # + 3 per nibble: a count >= 5 sets the nibble's bit 3 (no carry: 9 + 3 < 16)
_BIT3 = np.uint32(0x88888888)


@parallel_kernel(cache=True, error_model="numpy")
def _occupancy_kernel(d, bits):  # pragma: no cover
    L, H, W = d.shape
    for v in nb.prange(H):
        for u in range(W):
            b = 0
            for l in range(L):
                if d[l, v, u] > 0:
                    b |= 1 << l
            bits[v, u] = b


@parallel_kernel(cache=True, error_model="numpy")
def _occupancy_front_kernel(d, c, bits, zout, cp):  # pragma: no cover
    # _occupancy_kernel plus, from the same reads, the front-most surface of the layers (smallest
    # depth; ties to the lower layer): depth into zout (H, W), colour into the planes cp (3, H, W).
    # Same result as presim.synthesis.blend.front_of_layers (tested equal).
    L, H, W = d.shape
    for v in nb.prange(H):
        zr = zout[v]
        c0 = cp[0, v]
        c1 = cp[1, v]
        c2 = cp[2, v]
        for u in range(W):
            zb = d[0, v, u]
            b = 1 if zb > 0 else 0
            best = 0
            for l in range(1, L):
                z = d[l, v, u]
                if z > 0:
                    b |= 1 << l
                    if zb == 0 or z < zb:
                        zb = z
                        best = l
            bits[v, u] = b
            zr[u] = zb
            c0[u] = c[best, v, u, 0]
            c1[u] = c[best, v, u, 1]
            c2[u] = c[best, v, u, 2]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _ce(a, i, j):  # pragma: no cover
    x = a[i]
    y = a[j]
    a[i] = min(x, y)
    a[j] = max(x, y)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _sort8(a):  # pragma: no cover
    # Batcher's odd-even merge sort of 8 values (19 branch-free compare-exchanges).
    _ce(a, 0, 1)
    _ce(a, 2, 3)
    _ce(a, 4, 5)
    _ce(a, 6, 7)
    _ce(a, 0, 2)
    _ce(a, 1, 3)
    _ce(a, 4, 6)
    _ce(a, 5, 7)
    _ce(a, 1, 2)
    _ce(a, 5, 6)
    _ce(a, 0, 4)
    _ce(a, 1, 5)
    _ce(a, 2, 6)
    _ce(a, 3, 7)
    _ce(a, 2, 4)
    _ce(a, 3, 5)
    _ce(a, 1, 2)
    _ce(a, 3, 4)
    _ce(a, 5, 6)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _median8(d, c, l, y0, y1, x0, x1, bd, b0, b1, b2):  # pragma: no cover
    """Lower median (depth, each colour channel) of the non-empty pixels of layer ``l`` in the
    window, whose centre is empty (so at most 8 values): slots past the count are padded with the
    largest value, which leaves ranks below the count unchanged. Returns the median's index."""
    n = gather_window(d, c, l, y0, y1, x0, x1, bd, b0, b1, b2)
    for i in range(n, 8):
        bd[i] = np.inf
        b0[i] = 255
        b1[i] = 255
        b2[i] = 255
    _sort8(bd)
    _sort8(b0)
    _sort8(b1)
    _sort8(b2)
    return (n - 1) // 2


@parallel_kernel(cache=True, error_model="numpy")
def _packed_composite_kernel(d, c, bits, spread, need, use_need, dout, cout):  # pragma: no cover
    # Per-layer 3x3 switching median fused with the front-to-back composite, via packed counts.
    L, H, W = d.shape
    for v in nb.prange(H):
        y0 = max(v - 1, 0)
        y1 = min(v + 2, H)
        col = np.zeros(W + 2, np.uint32)  # col[u + 1] = packed counts of column u over rows y0..y1-1
        for y in range(y0, y1):
            for u in range(W):
                col[u + 1] += spread[bits[y, u]]
        bd = np.empty(8, np.float32)
        b0 = np.empty(8, np.uint8)
        b1 = np.empty(8, np.uint8)
        b2 = np.empty(8, np.uint8)
        for u in range(W):
            if use_need and not need[v, u]:
                dout[v, u] = 0.0  # never a value: stays empty for the seam pass's counts
                continue
            b = np.int64(bits[v, u])
            flags = (col[u] + col[u + 1] + col[u + 2] + _GE5) & _BIT3
            dout[v, u] = 0.0
            cout[v, u, 0] = 0
            cout[v, u, 1] = 0
            cout[v, u, 2] = 0
            if b == 0 and flags == 0:
                continue
            for l in range(L):
                if (b >> l) & 1:
                    dout[v, u] = d[l, v, u]
                    cout[v, u, 0] = c[l, v, u, 0]
                    cout[v, u, 1] = c[l, v, u, 1]
                    cout[v, u, 2] = c[l, v, u, 2]
                    break
                if (flags >> np.uint32(4 * l + 3)) & np.uint32(1):
                    k = _median8(d, c, l, y0, y1, max(u - 1, 0), min(u + 2, W), bd, b0, b1, b2)
                    dout[v, u] = bd[k]
                    cout[v, u, 0] = b0[k]
                    cout[v, u, 1] = b1[k]
                    cout[v, u, 2] = b2[k]
                    break


_ONES3 = np.ones((3, 3), np.uint8)


@parallel_kernel(cache=True, error_model="numpy")
def _packed_seam_kernel(d, c, mask, use_mask, dout, cout):  # pragma: no cover
    # 3x3 switching median of one image (the seam pass): each row of dout / cout is first a copy
    # of d / c, then its cracks get the median.
    H, W = d.shape
    d3 = d.reshape((1, H, W))
    c3 = c.reshape((1, H, W, 3))
    for v in nb.prange(H):
        dout[v] = d[v]
        cout[v] = c[v]
        y0 = max(v - 1, 0)
        y1 = min(v + 2, H)
        col = np.zeros(W + 2, np.int32)
        for y in range(y0, y1):
            for u in range(W):
                col[u + 1] += np.int32(d[y, u] > 0)
        bd = np.empty(8, np.float32)
        b0 = np.empty(8, np.uint8)
        b1 = np.empty(8, np.uint8)
        b2 = np.empty(8, np.uint8)
        for u in range(W):
            if col[u] + col[u + 1] + col[u + 2] < 5 or d[v, u] > 0:
                continue
            if use_mask and not mask[v, u]:
                continue
            k = _median8(d3, c3, 0, y0, y1, max(u - 1, 0), min(u + 2, W), bd, b0, b1, b2)
            dout[v, u] = bd[k]
            cout[v, u, 0] = b0[k]
            cout[v, u, 1] = b1[k]
            cout[v, u, 2] = b2[k]


def filtered_composite_packed(depth_m: np.ndarray, color: np.ndarray, replace: np.ndarray | None = None,
                              front: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3 x 3 switching median per layer + front-to-back composite + seam pass, crack mask first.

    Equals ``crack_filter`` (per layer, ``"switching_median"``, 3 x 3) -> :func:`composite_layers` ->
    ``crack_filter`` (seam pass) exactly, but the window of a pixel is only read where a median is
    actually taken (packed per-layer occupancy counts decide that, see above).

    Args:
        depth_m: float32 (L, H, W) warped layers (L <= :data:`PACKED_MAX_LAYERS`), 0 = empty;
            color: uint8 (L, H, W, 3).
        replace: optional bool (H, W): only these pixels' final values are wanted (the composite is
            then evaluated on ``replace`` grown by one pixel, all the seam pass reads); other
            pixels are UNDEFINED.
        front: optional ``(depth_out (H, W) float32, color_out (H, W, 3) uint8)``: also write the
            front-most surface of the layers there (smallest depth per pixel, no crack filter: what
            :func:`presim.synthesis.blend.front_of_layers` computes), from the same pass that reads
            the layers for the crack mask (blending keeps it; ``color_out`` may be planar memory).
    Returns:
        ``(depth_m (H, W), color (H, W, 3))``.
    """
    L, H, W = depth_m.shape
    if L > PACKED_MAX_LAYERS:
        raise ValueError(f"filtered_composite_packed: at most {PACKED_MAX_LAYERS} layers, got {L}")
    use = replace is not None
    need = _NO_MASK if not use else cv2.dilate(replace.view(np.uint8), _ONES3).view(bool)
    bits = np.empty((H, W), np.uint8)
    if front is None:
        _occupancy_kernel(depth_m, bits)
    else:
        _occupancy_front_kernel(depth_m, color, bits, front[0], front[1].transpose(2, 0, 1))
    # Depth outside ``need`` is written 0 (empty for the seam counts), colour there is left undefined.
    comp_d = np.empty((H, W), np.float32)
    comp_c = np.empty((H, W, 3), np.uint8)
    _packed_composite_kernel(depth_m, color, bits, _SPREAD, need, use, comp_d, comp_c)
    out_d = np.empty((H, W), np.float32)
    out_c = np.empty((H, W, 3), np.uint8)
    _packed_seam_kernel(comp_d, comp_c, replace if use else _NO_MASK, use, out_d, out_c)
    return out_d, out_c


# ---- the same three passes fused in row bands (one parallel region per view) ------------------
#
# filtered_composite_packed runs three image-wide passes (occupancy bits, filter + composite, seam
# pass) with full-size intermediates and copies between them. Here every thread takes bands of
# rows and does all three for its band in buffers that stay in cache: the occupancy bits of the
# band grown by 2 rows, the composite of the band grown by 1 row (what the seam pass reads), then
# the seam pass of the band itself. The rows of the halos are computed twice (by both bands that
# touch them); the arithmetic per pixel is that of the three kernels above, so the output is the
# same bit for bit.

TILE_COLS = 8
"""Columns per tile of :func:`filtered_composite_banded` with ``replace`` (a run of tiles holding
wanted pixels is one work item). With :data:`TILE_ROWS`, 8 x 8 tiles: a later view's crack pass
inside 640x480 frames took 0.74x (apc capture) and 0.94x (sample scene) the time of 32 x 32 tiles,
median (docs/synthesis.md, "Smaller crack tiles for later views")."""

TILE_ROWS = 8
"""Rows per band of :func:`filtered_composite_banded` on tiles (whole-width bands keep
:func:`_band_rows`). Small tiles follow the holes of a later view (small, scattered) closely; each
work item recomputes a 2-pixel halo, which costs more the smaller the tile."""

WARP_TILE_PX = 16
"""Side of the tiles :func:`warp_tiles` marks for a masked warp."""

TILED_MIN_PIXELS = 150_000
"""Images of at least this many pixels run a later view's crack pass on tiles (and its warp on
:func:`warp_tiles`); smaller ones on whole bands. Measured (benchmarks/bench_ab.py, apc capture
with refined depth, 2 threads): 1.25x less CPU per frame at 640x480, but 0.93x (CPU) and slower
wall time at 128x128 and 256x256, where a few uneven work items leave a thread idle."""


TILED_MAX_FRAC = 0.5
"""A later view uses tiles (crack pass and warp) only while at most this fraction of the tiles is
active: with speckled holes everywhere (raw depth with 34 % valid pixels: 81 % of the warp tiles
active) the tiles' bookkeeping cost more than they saved (apc capture, raw depth, 640x480: 0.76x)."""


def _band_rows(H: int) -> int:
    """Rows per band: 32 (6 % halo recomputation of the composite; 16-row bands made 128x128 frames
    slower: twice the halo rows and the per-band buffers)."""
    return 32


_LOWEST = np.array([0] + [(b & -b).bit_length() - 1 for b in range(1, 256)], np.int64)
"""Index of the lowest set bit of a byte (0 for 0)."""


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _rank23_of8(x0, x1, x2, x3, x4, x5, x6, x7):  # pragma: no cover
    # The compare-exchanges of _sort8 on scalars (kept in registers); returns sorted[2], sorted[3]
    # (the compiler drops the exchanges that cannot reach those two outputs).
    x0, x1 = min(x0, x1), max(x0, x1)
    x2, x3 = min(x2, x3), max(x2, x3)
    x4, x5 = min(x4, x5), max(x4, x5)
    x6, x7 = min(x6, x7), max(x6, x7)
    x0, x2 = min(x0, x2), max(x0, x2)
    x1, x3 = min(x1, x3), max(x1, x3)
    x4, x6 = min(x4, x6), max(x4, x6)
    x5, x7 = min(x5, x7), max(x5, x7)
    x1, x2 = min(x1, x2), max(x1, x2)
    x5, x6 = min(x5, x6), max(x5, x6)
    x0, x4 = min(x0, x4), max(x0, x4)
    x1, x5 = min(x1, x5), max(x1, x5)
    x2, x6 = min(x2, x6), max(x2, x6)
    x3, x7 = min(x3, x7), max(x3, x7)
    x2, x4 = min(x2, x4), max(x2, x4)
    x3, x5 = min(x3, x5), max(x3, x5)
    x1, x2 = min(x1, x2), max(x1, x2)
    x3, x4 = min(x3, x4), max(x3, x4)
    x5, x6 = min(x5, x6), max(x5, x6)
    return x2, x3


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _nb_value(df, cf, q):  # pragma: no cover
    # (depth, r, g, b, 1) of flat pixel q; an empty pixel reads as (+inf, 255, 255, 255, 0). All
    # loads unconditional and selects after them: no branch on the speckled occupancy.
    z = df[q]
    q3 = np.uint64(3) * q
    r = cf[q3]
    g = cf[q3 + np.uint64(1)]
    b = cf[q3 + np.uint64(2)]
    ok = z > 0
    e = np.uint8(255)
    return (z if ok else np.float32(np.inf)), (r if ok else e), (g if ok else e), (b if ok else e), np.int64(ok)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _median8_interior(df, cf, p, w, out_c):  # pragma: no cover
    """:func:`_median8` of the 3x3 window at an interior pixel whose centre is empty, without
    buffers: ``df`` / ``cf`` are one layer's (or image's) depth and colour, flat (colour 3 bytes
    per pixel), ``p`` the centre's flat index and ``w`` the row length (both uint64: no wraparound
    code). The 8 neighbours are read once into registers, empty ones as +inf / 255 (the padding
    :func:`_median8` uses), and ranks 2 and 3 of a sorting network give the lower median of the
    5..8 non-empty ones. Depth returned, colour into ``out_c``."""
    one = np.uint64(1)
    z0, r0, g0, b0, n0 = _nb_value(df, cf, p - w - one)
    z1, r1, g1, b1, n1 = _nb_value(df, cf, p - w)
    z2, r2, g2, b2, n2 = _nb_value(df, cf, p - w + one)
    z3, r3, g3, b3, n3 = _nb_value(df, cf, p - one)
    z4, r4, g4, b4, n4 = _nb_value(df, cf, p + one)
    z5, r5, g5, b5, n5 = _nb_value(df, cf, p + w - one)
    z6, r6, g6, b6, n6 = _nb_value(df, cf, p + w)
    z7, r7, g7, b7, n7 = _nb_value(df, cf, p + w + one)
    hi = n0 + n1 + n2 + n3 + n4 + n5 + n6 + n7 >= 7  # lower median of n values: rank 3 for n = 7, 8, else 2
    s2, s3 = _rank23_of8(r0, r1, r2, r3, r4, r5, r6, r7)
    out_r = s3 if hi else s2
    s2, s3 = _rank23_of8(g0, g1, g2, g3, g4, g5, g6, g7)
    out_g = s3 if hi else s2
    s2, s3 = _rank23_of8(b0, b1, b2, b3, b4, b5, b6, b7)
    out_b = s3 if hi else s2
    t2, t3 = _rank23_of8(z0, z1, z2, z3, z4, z5, z6, z7)
    out_c[0] = out_r
    out_c[1] = out_g
    out_c[2] = out_b
    return t3 if hi else t2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _crack_item(d, c, lowest, need, use_need, mask, a, e, x0, x1, dout, cout):  # pragma: no cover
    # One work item = rows [a, e) x columns [x0, x1) of the output (a band of rows over the whole
    # width, or a run of tiles that hold wanted pixels). Branch-free per pixel and layer (the
    # occupancy of warped layers is speckled: a branch per pixel and layer mispredicts often)
    # except one test "nothing here at all", which holds over whole regions; the pixels that need
    # a median are first collected into a list. An item reads the layers on its rectangle grown by
    # 2 pixels (clipped to the image). d and c must be C-contiguous.
    #
    # Inner loops index from 0 (k) into row slices taken at the item's offsets, and the gathers
    # from the layer a pixel takes use unsigned flat offsets: numba then emits no negative-index
    # wraparound code there (a third less time for the composite loop, docs/synthesis.md).
    L, H, W = d.shape
    r0 = max(a - 1, 0)  # composite rows [r0, r1) x cols [c0, c1): the item and the seam halo
    r1 = min(e + 1, H)
    c0 = max(x0 - 1, 0)
    c1 = min(x1 + 1, W)
    s0 = max(r0 - 1, 0)  # occupancy rows [s0, s1) x cols [o0, o1): what the composite's counts read
    s1 = min(r1 + 1, H)
    o0 = max(c0 - 1, 0)
    o1 = min(c1 + 1, W)
    nw = c1 - c0
    no = o1 - o0
    HW = H * W
    dflat = d.reshape(L * HW)
    cflat = c.reshape(L * HW * 3)
    uW = np.uint64(W)
    # Occupancy: bit l of bits = layer l non-empty; sp = the same bits spread to 4-bit counters
    # (bit l -> nibble l, = _SPREAD[bits]), so that a 3x3 window's per-layer counts are sums of sp
    # without carries (<= 9 per nibble). Both from comparisons alone (no table lookups: vectorized).
    bits = np.empty((s1 - s0, no), np.uint8)
    sp = np.empty((s1 - s0, no), np.uint32)
    for y in range(s0, s1):
        br = bits[y - s0]
        spr = sp[y - s0]
        d0 = d[0, y, o0:o1]
        for k in range(no):
            o = d0[k] > 0
            br[k] = np.uint8(o)
            spr[k] = np.uint32(o)
        for l in range(1, L):
            dl = d[l, y, o0:o1]
            s8 = np.uint8(l)
            s32 = np.uint32(4 * l)
            for k in range(no):
                o = dl[k] > 0
                br[k] |= np.uint8(o) << s8
                spr[k] |= np.uint32(o) << s32
    nr = r1 - r0
    comp_d = np.empty((nr, nw), np.float32)
    comp_c = np.empty((nr, nw, 3), np.uint8)
    col = np.zeros(nw + 2, np.uint32)  # col[u - c0 + 1]: packed counts of column u (0 outside the image)
    off = o0 - c0 + 1  # col index of occupancy column o0 (0, or 1 at the image's left edge)
    ni = x1 - x0
    icol = np.zeros(ni + 2, np.int32)  # icol[u - x0 + 1]: non-empty composite pixels of column u
    ioff = c0 - x0 + 1  # icol index of composite column c0
    med_u = np.empty(nw, np.int64)
    med_l = np.empty(nw, np.int64)
    mrow = np.empty(nw, np.uint8)
    bd = np.empty(8, np.float32)
    b0 = np.empty(8, np.uint8)
    b1 = np.empty(8, np.uint8)
    b2 = np.empty(8, np.uint8)
    px = np.empty(3, np.uint8)
    for v in range(r0, r1):
        y0 = max(v - 1, 0)
        y1 = min(v + 2, H)
        col[0] = 0
        col[nw + 1] = 0
        spy = sp[y0 - s0]
        for k in range(no):
            col[k + off] = spy[k]
        for y in range(y0 + 1, y1):
            spy = sp[y - s0]
            for k in range(no):
                col[k + off] += spy[k]
        zr = comp_d[v - r0]
        cr = comp_c[v - r0]
        brk = bits[v - s0, c0 - o0:]
        vb = v * W + c0
        dk = dflat[vb:]  # dk[l * HW + k]: layer l at column c0 + k of row v
        ck = cflat[3 * vb:]
        needk = need[v, c0:c1] if use_need else need[0, 0:0]
        # Per pixel: bit l of m = layer l has a value here or takes a median here (uint32
        # arithmetic on whole rows: vectorized); the gathers follow in a second loop.
        for k in range(nw):
            f = (col[k] + col[k + 1] + col[k + 2] + _GE5) & _BIT3
            x = (f >> np.uint32(3)) & np.uint32(0x11111111)  # bits 4l + 3 of f -> bit l of a byte
            x = (x | (x >> np.uint32(3))) & np.uint32(0x03030303)
            x = (x | (x >> np.uint32(6))) & np.uint32(0x000F000F)
            x = (x | (x >> np.uint32(12))) & np.uint32(0xFF)
            mrow[k] = np.uint8(x) | brk[k]
        if use_need:
            for k in range(nw):
                mrow[k] = mrow[k] * np.uint8(needk[k])
        nm = 0
        for k in range(nw):
            m = np.int64(mrow[k])
            if m == 0:  # empty and no median due (most pixels outside the covered region):
                zr[k] = 0.0  # one well-predicted branch beats the gathers below there
                cr[k, 0] = 0
                cr[k, 1] = 0
                cr[k, 2] = 0
                continue
            b = np.int64(brk[k])
            l = lowest[m]
            hit = (m >> l) & (b >> l) & 1  # 0 / 1: arithmetic selects below, no branches
            p = np.uint64(l * HW + k)
            zr[k] = dk[p] * np.float32(hit)
            hc = np.uint8(hit)
            p3 = np.uint64(3) * p
            cr[k, 0] = ck[p3] * hc
            cr[k, 1] = ck[p3 + np.uint64(1)] * hc
            cr[k, 2] = ck[p3 + np.uint64(2)] * hc
            med_u[nm] = k + c0
            med_l[nm] = l
            nm += hit ^ 1
        inner_v = 0 < v < H - 1
        for i in range(nm):
            u = med_u[i]
            k = u - c0
            if inner_v and 0 < u < W - 1:
                zr[k] = _median8_interior(dflat, cflat, np.uint64(med_l[i] * HW + v * W + u), uW, px)
                cr[k, 0] = px[0]
                cr[k, 1] = px[1]
                cr[k, 2] = px[2]
                continue
            j = _median8(d, c, med_l[i], y0, y1, max(u - 1, 0), min(u + 2, W), bd, b0, b1, b2)
            zr[k] = bd[j]
            cr[k, 0] = b0[j]
            cr[k, 1] = b1[j]
            cr[k, 2] = b2[j]
    # Seam pass over the item: 3x3 switching median of the composite.
    cd3 = comp_d.reshape((1, nr, nw))
    cc3 = comp_c.reshape((1, nr, nw, 3))
    cdf = comp_d.reshape(nr * nw)
    ccf = comp_c.reshape(nr * nw * 3)
    unw = np.uint64(nw)
    coutf = cout.reshape(H * W * 3)
    for v in range(a, e):
        y0 = max(v - 1, 0)
        y1 = min(v + 2, H)
        for k in range(ni + 2):
            icol[k] = 0
        for y in range(y0, y1):
            zy = comp_d[y - r0]
            for k in range(nw):
                icol[k + ioff] += np.int32(zy[k] > 0)
        zs = comp_d[v - r0, x0 - c0:]  # zs[k]: composite depth at column x0 + k
        do = dout[v, x0:x1]
        for k in range(ni):
            do[k] = zs[k]
        cof = coutf[3 * (v * W + x0):3 * (v * W + x1)]  # the colour row as bytes: one flat copy
        csf = ccf[3 * ((v - r0) * nw + x0 - c0):]
        for t in range(3 * ni):
            cof[t] = csf[t]
        mk = mask[v, x0:x1] if use_need else mask[0, 0:0]
        nm = 0
        for k in range(ni):
            want = (np.int64(zs[k] > 0) ^ 1) & np.int64(icol[k] + icol[k + 1] + icol[k + 2] >= 5)
            if use_need:
                want = want & np.int64(mk[k])
            med_u[nm] = k + x0
            nm += want
        inner_v = 0 < v < H - 1
        for i in range(nm):
            u = med_u[i]
            if inner_v and 0 < u < W - 1:
                dout[v, u] = _median8_interior(cdf, ccf, np.uint64((v - r0) * nw + u - c0), unw, px)
                cout[v, u, 0] = px[0]
                cout[v, u, 1] = px[1]
                cout[v, u, 2] = px[2]
                continue
            j = _median8(cd3, cc3, 0, y0 - r0, y1 - r0, max(u - 1, 0) - c0, min(u + 2, W) - c0, bd, b0, b1, b2)
            dout[v, u] = bd[j]
            cout[v, u, 0] = b0[j]
            cout[v, u, 1] = b1[j]
            cout[v, u, 2] = b2[j]


@parallel_kernel(cache=True, error_model="numpy")
def _banded_crack_kernel(d, c, lowest, need, use_need, mask, band, dout, cout):  # pragma: no cover
    # Bands of ``band`` rows over the whole width (constant columns: the compiler drops the offsets).
    H, W = d.shape[1], d.shape[2]
    for bi in nb.prange((H + band - 1) // band):
        _crack_item(d, c, lowest, need, use_need, mask, bi * band, min(bi * band + band, H), 0, W, dout, cout)


@parallel_kernel(cache=True, error_model="numpy")
def _tiled_crack_kernel(d, c, lowest, need, use_need, mask, items, dout, cout):  # pragma: no cover
    # Work items = rows [a, e) x columns [x0, x1) (runs of tiles holding wanted pixels).
    for it in nb.prange(items.shape[0]):
        _crack_item(d, c, lowest, need, use_need, mask, items[it, 0], items[it, 1], items[it, 2],
                    items[it, 3], dout, cout)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _tile_any_kernel(mask, tile_h, tile_w, grow):  # pragma: no cover
    # Per tile: its rectangle grown by ``grow`` (clipped), scanned pixel by pixel up to the first
    # nonzero one (on a big-endian machine, where the words' byte order differs; tested on all).
    H, W = mask.shape
    th = (H + tile_h - 1) // tile_h
    tw = (W + tile_w - 1) // tile_w
    out = np.zeros((th, tw), np.uint8)
    for ty in range(th):
        ya = max(ty * tile_h - grow, 0)
        yb = min((ty + 1) * tile_h + grow, H)
        for tx in range(tw):
            xa = max(tx * tile_w - grow, 0)
            xb = min((tx + 1) * tile_w + grow, W)
            found = False
            for v in range(ya, yb):
                row = mask[v]
                for u in range(xa, xb):
                    if row[u]:
                        found = True
                        break
                if found:
                    break
            if found:
                out[ty, tx] = 1
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _tile_any_words_kernel(words, H, W, tile_h, tile_w, grow):  # pragma: no cover
    # tile_any from the mask's rows as uint64 words (8 pixels each, little-endian: pixel 8k + j is
    # byte j of word k): per row of tiles, the OR of the words of its grown rows; per tile, the OR
    # of the words its grown columns touch, the bytes outside them masked off. A nonzero byte
    # survives an OR, so the result is nonzero exactly when a pixel of the rectangle is.
    th = (H + tile_h - 1) // tile_h
    tw = (W + tile_w - 1) // tile_w
    nw = words.shape[1]
    out = np.zeros((th, tw), np.uint8)
    band = np.empty(nw, np.uint64)
    ones = np.uint64(0xFFFFFFFFFFFFFFFF)
    one = np.uint64(1)
    zero = np.uint64(0)
    for ty in range(th):
        ya = max(ty * tile_h - grow, 0)
        yb = min((ty + 1) * tile_h + grow, H)
        band[:] = zero
        for v in range(ya, yb):
            wrow = words[v]
            for k in range(nw):
                band[k] |= wrow[k]
        for tx in range(tw):
            xa = max(tx * tile_w - grow, 0)
            xb = min((tx + 1) * tile_w + grow, W)
            wa = xa // 8
            wb = (xb + 7) // 8
            acc = zero
            for k in range(wa, wb):
                w = band[k]
                if k == wa:  # drop the pixels left of xa
                    w &= ones << np.uint64(8 * (xa - 8 * wa))
                if k == wb - 1 and xb < 8 * wb:  # and those from xb on
                    w &= (one << np.uint64(8 * (xb - 8 * k))) - one
                acc |= w
            out[ty, tx] = acc != zero
    return out


_LITTLE = sys.byteorder == "little"


def tile_any(mask: np.ndarray, tile_h: int, tile_w: int, grow: int) -> np.ndarray:
    """uint8 (ceil(H / tile_h), ceil(W / tile_w)): 1 where a nonzero pixel of ``mask`` (uint8 or
    bool, H x W) lies within ``grow`` pixels (Chebyshev distance) of the tile (numba; reference
    :func:`presim.synthesis.kernels_reference.tile_any_ref`).

    Each tile looks at its rectangle grown by ``grow``. On little-endian machines: the OR of the
    rows of each row of tiles as 8-pixel words (:func:`_row_words`: rows whose width is not a
    multiple of 8 are copied with zero padding first), then per tile the OR of the words it covers
    (one pass over the mask whatever its density: 13 against 102 us per 640x480 replace mask of
    the apc capture for the per-tile scan below, median of 66). Otherwise each tile scans its
    rectangle pixel by pixel up to the first nonzero one; marking tiles from every nonzero pixel
    cost ~5 ns per nonzero pixel (1.4 ms for a 640x480 mask 30 % full).
    """
    m = np.ascontiguousarray(mask).view(np.uint8)
    H, W = m.shape
    if W and _LITTLE:
        return _tile_any_words_kernel(_row_words(m), H, W, int(tile_h), int(tile_w), int(grow))
    return _tile_any_kernel(m, int(tile_h), int(tile_w), int(grow))


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _tile_items_kernel(active, tile_h, tile_w, H, W):  # pragma: no cover
    # Runs of consecutive active tiles along each row of tiles -> (n, 4): rows [a, e), cols [x0, x1).
    th, tw = active.shape
    out = np.empty((th * tw, 4), np.int64)
    n = 0
    for ty in range(th):
        tx = 0
        while tx < tw:
            if active[ty, tx] == 0:
                tx += 1
                continue
            t0 = tx
            while tx < tw and active[ty, tx] != 0:
                tx += 1
            out[n, 0] = ty * tile_h
            out[n, 1] = min((ty + 1) * tile_h, H)
            out[n, 2] = t0 * tile_w
            out[n, 3] = min(tx * tile_w, W)
            n += 1
    return out[:n].copy()


def filtered_composite_banded(depth_m: np.ndarray, color: np.ndarray, replace: np.ndarray | None = None,
                              band_rows: int | None = None, tile_cols: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`filtered_composite_packed` (without ``front``) in one pass over bands of rows.

    Same output bit for bit on every pixel the packed chain defines (all pixels without
    ``replace``; the ``replace`` pixels with it — others are UNDEFINED here too), tested against
    it and against the numpy reference chain. Occupancy, composite and seam pass of a band run in
    buffers of the band (no full-size intermediates, no copies, one parallel region). With
    ``replace``, a band is cut into tiles of ``tile_cols`` columns and only runs of tiles holding a
    ``replace`` pixel are computed; the layers are then read only within 2 pixels of those tiles'
    ``replace`` pixels' neighbourhoods (:func:`warp_tiles` marks a superset), so the layers may be
    undefined elsewhere (:func:`presim.synthesis.warp.warp_layers` with ``tiles``).

    Args:
        depth_m: float32 (L, H, W) warped layers (L <= :data:`PACKED_MAX_LAYERS`); color: uint8 (L, H, W, 3).
        replace: optional bool (H, W): the pixels whose values are wanted.
        band_rows: rows per band (default :func:`_band_rows`; any value >= 1 gives the same output).
        tile_cols: columns per tile with ``replace`` (None: :data:`TILE_COLS` from
            :data:`TILED_MIN_PIXELS` pixels on while at most :data:`TILED_MAX_FRAC` of the tiles
            hold a ``replace`` pixel, else whole rows; any value >= 1 gives the same output). On
            tiles, the bands are ``band_rows`` rows high (None: :data:`TILE_ROWS`).
    Returns:
        ``(depth_m (H, W), color (H, W, 3))``.
    """
    L, H, W = depth_m.shape
    if L > PACKED_MAX_LAYERS:
        raise ValueError(f"filtered_composite_banded: at most {PACKED_MAX_LAYERS} layers, got {L}")
    depth_m = np.ascontiguousarray(depth_m)  # the kernel indexes the layers flat (no copy when they are)
    color = np.ascontiguousarray(color)
    use = replace is not None
    explicit_tiles = tile_cols is not None
    if tile_cols is None:
        tile_cols = TILE_COLS if H * W >= TILED_MIN_PIXELS else W
    band = max(int(band_rows) if band_rows else _band_rows(H), 1)
    tile_band = max(int(band_rows) if band_rows else TILE_ROWS, 1)
    if use:
        need = cv2.dilate(replace.view(np.uint8), _ONES3).view(bool)
        mask = replace
    else:
        need = mask = np.zeros((1, 1), np.bool_)
    tw = max(int(tile_cols), 1)
    out_d = np.empty((H, W), np.float32)
    out_c = np.empty((H, W, 3), np.uint8)
    active = tile_any(replace.view(np.uint8), tile_band, tw, 0) if use and tw < W else None
    if active is not None and (explicit_tiles or active.mean() <= TILED_MAX_FRAC):
        items = _tile_items_kernel(active, tile_band, tw, H, W)
        if len(items):
            _tiled_crack_kernel(depth_m, color, _LOWEST, need, use, mask, items, out_d, out_c)
    else:
        _banded_crack_kernel(depth_m, color, _LOWEST, need, use, mask, band, out_d, out_c)
    return out_d, out_c


def warp_tiles(replace: np.ndarray, tile_px: int = WARP_TILE_PX) -> np.ndarray:
    """uint8 (ceil(H / tile_px), ceil(W / tile_px)): the tiles of ``tile_px`` x ``tile_px`` pixels
    within 2 pixels of a ``replace`` pixel — every layer pixel :func:`filtered_composite_banded`
    reads for the ``replace`` pixels (the 3 x 3 windows of the composite pixels in the 3 x 3
    windows of the seam pass). :func:`presim.synthesis.warp.warp_layers` warps and clears only
    those (``tiles=``)."""
    return tile_any(replace.view(np.uint8), tile_px, tile_px, 2)
