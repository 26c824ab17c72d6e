"""Crack filling and compositing of one view's warped layers (thesis eq. 3.9, §3.4.3-3.4.4).

The switching median fills an empty pixel whose N x N window is more than half non-empty with the lower median of
the non-empty depths and of each colour channel; the plain median (``"median"``) filters every pixel over its
zero-padded window. Layers are filtered alone, composited front to back, then filtered once more for the seams.
Rules and the reference: :mod:`kernels_reference` (:func:`crack_filter`: any mode and window);
:func:`filtered_composite_banded` fuses the default (3 x 3 switching, <= 8 layers) per band, bit-identical."""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np

from presim.imaging.masks import tile_any
from presim.numba_threads import parallel_kernel
from presim.synthesis import kernels_reference as ref
from presim.synthesis.config import CRACK_FILTERS

__all__ = ["BANDED_MAX_LAYERS", "TILED_MIN_PIXELS", "TILED_MAX_FRAC", "WARP_TILE_PX",
           "crack_filter", "filtered_composite_banded", "warp_tiles"]


BANDED_MAX_LAYERS = 8
"""The banded pass packs a pixel's per-layer occupancy into one byte: at most 8 layers."""

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
    """Copy the non-empty pixels of layer ``l`` in rows [y0, y1) x cols [x0, x1) into bd, b0-b2; returns n."""
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
    """Sort the first n depths and each colour channel separately (eq. 3.9); returns the lower median's index."""
    _insertion_sort(bd, n)
    _insertion_sort(b0, n)
    _insertion_sort(b1, n)
    _insertion_sort(b2, n)
    return (n - 1) // 2


def crack_filter(depth_m: np.ndarray, color: np.ndarray, mode: str = "switching_median",
                 kernel_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Fill cracks of float32 (L, H, W) or (H, W) depth (0 = empty) and uint8 colour: new arrays (the inputs
    for ``"none"``); ``mode`` in :data:`~presim.synthesis.config.CRACK_FILTERS`, odd window ``kernel_px``. The
    numpy reference (~0.1 s per 640x480 layer): the renderer's default runs :func:`filtered_composite_banded`."""
    if mode not in CRACK_FILTERS:
        raise ValueError(f"crack filter must be one of {CRACK_FILTERS}, got {mode!r}")
    if kernel_px < 1 or kernel_px % 2 == 0:
        raise ValueError(f"kernel_px must be odd and >= 1, got {kernel_px}")
    if mode == "none":
        return depth_m, color
    if depth_m.dtype != np.float32 or color.dtype != np.uint8 or color.shape != depth_m.shape + (3,) \
            or depth_m.ndim not in (2, 3):
        raise ValueError(f"need float32 depth (L,H,W) or (H,W) and uint8 color (...,3), got {depth_m.dtype} "
                         f"{depth_m.shape}, {color.dtype} {color.shape}")
    filt = ref.switching_median_ref if mode == "switching_median" else ref.plain_median_ref
    if depth_m.ndim == 2:
        return filt(depth_m, color, kernel_px)
    pairs = [filt(d, c, kernel_px) for d, c in zip(depth_m, color)]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


# ---- 3 x 3 switching median on up to 8 layers: occupancy counts packed in nibbles -------------
#
# An empty pixel of layer l is filled when >= 5 of its 9 window pixels are non-empty in l. Per pixel, nibble l
# of a uint32 flags layer l non-empty, so the 3 x 3 counts of all layers are 9 integer additions (column sums
# reused along the row); ``(P + 3) & 8`` per nibble flags counts >= 5. Only those pixels gather and sort a
# window; every other pixel takes its nearest non-empty layer without reading neighbours.

_GE5 = np.uint32(0x33333333)  # + 3 per nibble: a count >= 5 sets the nibble's bit 3 (no carry: 9 + 3 < 16)
_BIT3 = np.uint32(0x88888888)


_ONES3 = np.ones((3, 3), np.uint8)

# ---- the three passes fused per work item (band of rows, or run of tiles), one parallel region ----
#
# Each item computes occupancy bits (its rows grown by 2), composite (grown by 1: what the seam pass reads) and
# seam pass in buffers that stay in cache. Halo rows are computed by both items touching them; the per-pixel
# arithmetic is that of crack_filter + composite_layers_ref + crack_filter, so the output is bit-identical.

BAND_ROWS = 32
"""Rows per band of the whole-width work items (6 % halo recomputation; 16 is slower at 128x128)."""

TILE_COLS = 8
"""Columns per tile with ``replace``: 8 x 8 tiles take 0.74x (apc) / 0.94x (sample) the time of 32 x 32 at 640x480."""

TILE_ROWS = 8
"""Rows per band on tiles: small tiles follow scattered holes, but each item recomputes a 2-pixel halo."""

WARP_TILE_PX = 16
"""Side of the tiles :func:`warp_tiles` marks for a tiled warp (``warp_layers(tiles=)``)."""

TILED_MIN_PIXELS = 150_000
"""Frames of at least this many pixels run a later view's crack pass and warp on tiles (apc 640x480: 1.21x
faster, bench_ab; smaller frames lose to uneven work items)."""

TILED_MAX_FRAC = 0.5
"""Tiles are used only while at most this fraction is active (raw apc depth, 81 % active: 0.76x)."""

LOWEST_SET_BIT = np.array([0] + [(b & -b).bit_length() - 1 for b in range(1, 256)], np.int64)
"""Index of the lowest set bit of a byte (0 for 0)."""


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _rank23_of8(x0, x1, x2, x3, x4, x5, x6, x7):  # pragma: no cover
    # Batcher's odd-even merge sort of 8 values on scalars (registers); returns sorted[2], sorted[3]
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
    # (depth, r, g, b, 1) of flat pixel q, (+inf, 255, 255, 255, 0) if empty; loads, then selects: no branch
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
    """Lower median of the 3x3 window at an interior pixel with empty centre, in registers: ``df`` / ``cf`` flat
    depth / colour of one layer or image, ``p`` the centre, ``w`` the row length (uint64: no wraparound code).
    Empty neighbours read as +inf / 255. Returns the depth; colour into ``out_c``."""
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
    # Work item = output rows [a, e) x columns [x0, x1) (a whole-width band, or a run of tiles holding wanted
    # pixels); reads the layers on it grown by 2 pixels (clipped); d, c C-contiguous. Branch-free per pixel and
    # layer (speckled occupancy mispredicts) except one "nothing here" test that holds over whole regions;
    # pixels needing a median are listed first. Inner loops index from 0 into row slices and gathers use unsigned
    # flat offsets: no negative-index wraparound code (a third less time for the composite loop).
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
    # Occupancy: bit l of bits / nibble l of sp = layer l non-empty (3x3 sums of sp: <= 9 per nibble, no
    # carries), from comparisons alone (no table lookups: vectorized).
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
        # bit l of m = layer l has a value or takes a median here (uint32 on whole rows: vectorized); gathers after
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
            n = gather_window(d, c, med_l[i], y0, y1, max(u - 1, 0), min(u + 2, W), bd, b0, b1, b2)
            j = sort_window(bd, b0, b1, b2, n)
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
            n = gather_window(cd3, cc3, 0, y0 - r0, y1 - r0, max(u - 1, 0) - c0, min(u + 2, W) - c0, bd, b0, b1, b2)
            j = sort_window(bd, b0, b1, b2, n)
            dout[v, u] = bd[j]
            cout[v, u, 0] = b0[j]
            cout[v, u, 1] = b1[j]
            cout[v, u, 2] = b2[j]


@parallel_kernel(cache=True, error_model="numpy")
def banded_crack_kernel(d, c, lowest, need, use_need, mask, band, dout, cout):  # pragma: no cover
    # Bands of ``band`` rows over the whole width (constant columns: the compiler drops the offsets).
    H, W = d.shape[1], d.shape[2]
    for bi in nb.prange((H + band - 1) // band):
        _crack_item(d, c, lowest, need, use_need, mask, bi * band, min(bi * band + band, H), 0, W, dout, cout)


@parallel_kernel(cache=True, error_model="numpy")
def tiled_crack_kernel(d, c, lowest, need, use_need, mask, items, dout, cout):  # pragma: no cover
    # Work items = rows [a, e) x columns [x0, x1) (runs of tiles holding wanted pixels).
    for it in nb.prange(items.shape[0]):
        _crack_item(d, c, lowest, need, use_need, mask, items[it, 0], items[it, 1], items[it, 2],
                    items[it, 3], dout, cout)


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
                              band_rows: int | None = None, tile_cols: int | None = None
                              ) -> tuple[np.ndarray, np.ndarray]:
    """3 x 3 switching median per layer, composite and seam pass fused per band of :data:`BANDED_MAX_LAYERS` <= 8
    layers: ``(depth_m (H, W), color (H, W, 3))``, bit-identical to the :func:`crack_filter` chain (tested).

    With ``replace`` (bool (H, W)) only those pixels are defined: on large frames only runs of ``tile_cols`` x
    ``band_rows`` tiles holding one are computed, reading the layers within 2 px of them (:func:`warp_tiles`).
    ``band_rows`` / ``tile_cols`` (None: :data:`BAND_ROWS` / :data:`TILE_ROWS`, :data:`TILE_COLS`) never change
    the output."""
    L, H, W = depth_m.shape
    if L > BANDED_MAX_LAYERS:
        raise ValueError(f"filtered_composite_banded: at most {BANDED_MAX_LAYERS} layers, got {L}")
    depth_m = np.ascontiguousarray(depth_m)  # the kernel indexes the layers flat (no copy when they are)
    color = np.ascontiguousarray(color)
    use = replace is not None
    explicit_tiles = tile_cols is not None
    if tile_cols is None:
        tile_cols = TILE_COLS if H * W >= TILED_MIN_PIXELS else W
    band = max(int(band_rows) if band_rows else BAND_ROWS, 1)
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
            tiled_crack_kernel(depth_m, color, LOWEST_SET_BIT, need, use, mask, items, out_d, out_c)
    else:
        banded_crack_kernel(depth_m, color, LOWEST_SET_BIT, need, use, mask, band, out_d, out_c)
    return out_d, out_c


def warp_tiles(replace: np.ndarray, tile_px: int = WARP_TILE_PX) -> np.ndarray:
    """uint8 tiles within 2 px of a ``replace`` pixel: every layer pixel :func:`filtered_composite_banded` reads
    for them (3 x 3 windows of 3 x 3 windows); :func:`presim.synthesis.warp.warp_layers` ``tiles=``."""
    return tile_any(replace.view(np.uint8), tile_px, tile_px, 2)
