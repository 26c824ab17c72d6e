"""Layered 3D warping (thesis §3.4.3, eq. 3.7-3.8) with a per-layer z-buffer: numba fast path.

Per-view data is prepared once (:func:`prepare_view`): the valid pixels of an input depth map are
back-projected to world points (eq. 3.7, via :func:`presim.geometry.unproject_depth`), given a layer
index (``num_layers`` equal slices between the map's min and max depth, thesis Fig. 3.8) and sorted
by layer so each layer is one contiguous slice. Per frame, :func:`warp_layers` projects the points
into the target camera (eq. 3.8) and z-buffers each in its own layer's image, skipping the runs of
:data:`CHUNK_PTS` points whose bounding box :func:`chunk_visibility` proves outside the target (same
output as projecting every point: ``cull=False``, tested).

The numba kernel re-states the pinhole projection of :func:`presim.geometry.project` inline (a call
per point would cost more than the arithmetic); tests check it against the reference, which uses
geometry.py. Layers are independent, so the kernel runs them in parallel (``prange``), race-free.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba as nb
import numpy as np

from presim.geometry import Intrinsics, unproject_depth
from presim.synthesis.threads import parallel_kernel

__all__ = ["CHUNK_PTS", "ViewPoints", "LayeredImage", "assign_layers", "chunk_bounds", "chunk_visibility", "layer_slots",
           "prepare_view", "prepare_view_ref", "warp_layers"]

CHUNK_PTS = 64
"""Points per chunk of a prepared view: consecutive points (source raster order within a layer, so
a chunk is a short run of neighbouring source pixels) whose world bounding box the warp tests
against the target frustum (:func:`chunk_visibility`) before it projects them."""


@nb.njit(cache=True, nogil=True)
def _chunk_bounds_kernel(xyz, chunk):  # pragma: no cover
    n = xyz.shape[0]
    m = (n + chunk - 1) // chunk
    lo = np.empty((m, 3), np.float32)
    hi = np.empty((m, 3), np.float32)
    for c in range(m):
        a = c * chunk
        b = min(n, a + chunk)
        for k in range(3):
            mn = xyz[a, k]
            mx = mn
            for i in range(a + 1, b):
                x = xyz[i, k]
                mn = min(mn, x)
                mx = max(mx, x)
            lo[c, k] = mn
            hi[c, k] = mx
    return lo, hi


def chunk_bounds(xyz_world: np.ndarray, chunk: int = CHUNK_PTS) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned bounds of each run of ``chunk`` consecutive points (the last run may be
    shorter): ``(lo, hi)``, float32 (ceil(n / chunk), 3) each."""
    xyz = np.ascontiguousarray(xyz_world, np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"chunk_bounds: need (n, 3) points, got {xyz.shape}")
    if chunk < 1:
        raise ValueError(f"chunk_bounds: chunk must be >= 1, got {chunk}")
    return _chunk_bounds_kernel(xyz, int(chunk))


@dataclass(frozen=True)
class ViewPoints:
    """One input view prepared for warping (cached by the Renderer, never rebuilt per frame)."""

    xyz_world: np.ndarray
    """float32 (n, 3) world points of the view's valid depth pixels, sorted by layer."""
    rgb: np.ndarray
    """uint8 (n, 3) their colors."""
    layer_start: np.ndarray
    """int64 (L + 1,): points of layer l are ``[layer_start[l], layer_start[l + 1])``."""
    depth_range_m: tuple[float, float]
    """(min, max) valid depth of the view, metres (the layer split)."""
    chunk_lo: np.ndarray = field(init=False, repr=False, compare=False)
    """float32 (ceil(n / CHUNK_PTS), 3): world lower bounds of each run of :data:`CHUNK_PTS` points
    (derived from ``xyz_world`` on construction, :func:`chunk_bounds`)."""
    chunk_hi: np.ndarray = field(init=False, repr=False, compare=False)
    """float32, the upper bounds."""

    def __post_init__(self) -> None:
        lo, hi = chunk_bounds(self.xyz_world)
        object.__setattr__(self, "chunk_lo", lo)
        object.__setattr__(self, "chunk_hi", hi)

    @property
    def num_layers(self) -> int:
        return int(self.layer_start.shape[0] - 1)

    @property
    def layer(self) -> np.ndarray:
        """(n,) int64 layer index of each point."""
        return np.repeat(np.arange(self.num_layers), np.diff(self.layer_start))

    @property
    def nbytes(self) -> int:
        return int(self.xyz_world.nbytes + self.rgb.nbytes + self.layer_start.nbytes + self.chunk_lo.nbytes
                   + self.chunk_hi.nbytes)


@dataclass(frozen=True)
class LayeredImage:
    """L warped images of one view in the target camera."""

    depth_m: np.ndarray
    """float32 (L, H, W) z-depth, 0 = empty."""
    color: np.ndarray
    """uint8 (L, H, W, 3)."""
    pix: np.ndarray | None = None
    """Scratch of :func:`warp_layers` (int64, at least one per point): each point's flat target pixel."""
    z: np.ndarray | None = None
    """Scratch of :func:`warp_layers` (float32): each point's target depth."""


def assign_layers(depth_m: np.ndarray, num_layers: int) -> tuple[np.ndarray, tuple[float, float]]:
    """Layer of each depth value: ``num_layers`` equal slices of [min, max] (layer 0 = nearest).

    Args:
        depth_m: (n,) valid depth values (> 0), metres.
    Returns:
        ``(layer (n,) int64, (min, max))``.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    if num_layers < 1:
        raise ValueError(f"num_layers must be >= 1, got {num_layers}")
    if d.size == 0:
        return np.zeros(0, np.int64), (0.0, 0.0)
    lo, hi = float(d.min()), float(d.max())
    if hi <= lo:
        return np.zeros(d.shape, np.int64), (lo, hi)
    layer = np.minimum(((d - lo) / (hi - lo) * num_layers).astype(np.int64), num_layers - 1)
    return layer, (lo, hi)


def prepare_view_ref(color: np.ndarray, depth_m: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                 num_layers: int) -> ViewPoints:
    """Reference (numpy, via geometry.py) of :func:`prepare_view`.

    Args:
        color: uint8 (h, w, 3); depth_m: float32 (h, w), 0 = invalid; K: the view's intrinsics.
        T_world_cam: 4x4 pose of the view.
    """
    if color.shape != (K.height, K.width, 3) or color.dtype != np.uint8:
        raise ValueError(f"color must be uint8 {K.height}x{K.width}x3, got {color.dtype} {color.shape}")
    pts, mask = unproject_depth(K, depth_m, T_world_cam)
    d = np.asarray(depth_m)[mask]
    layer, rng = assign_layers(d, num_layers)
    # Stable sort of small integer keys: numpy uses a radix sort for 8/16-bit ints (~10x faster).
    key = layer.astype(np.uint8 if num_layers <= 255 else np.uint16)
    order = np.argsort(key, kind="stable")
    counts = np.bincount(layer, minlength=num_layers)
    start = np.zeros(num_layers + 1, np.int64)
    start[1:] = np.cumsum(counts)
    return ViewPoints(np.ascontiguousarray(pts[order], np.float32),
                      np.ascontiguousarray(color[mask][order], np.uint8), start, rng)


@nb.njit(cache=True, nogil=True)  # nogil: views are also prepared in a background thread
def _prepare_kernel(depth, color, fx, fy, cx, cy, T, num_layers):  # pragma: no cover
    H, W = depth.shape
    n = 0
    lo = np.inf
    hi = -np.inf
    for v in range(H):
        for u in range(W):
            d = depth[v, u]
            if np.isfinite(d) and d > 0:
                n += 1
                dd = np.float64(d)
                lo = min(lo, dd)
                hi = max(hi, dd)
    counts = np.zeros(num_layers, np.int64)
    span = hi - lo
    if n:
        for v in range(H):
            for u in range(W):
                d = depth[v, u]
                if np.isfinite(d) and d > 0:
                    layer = 0
                    if span > 0:
                        layer = min(np.int64((np.float64(d) - lo) / span * num_layers), num_layers - 1)
                    counts[layer] += 1
    start = np.zeros(num_layers + 1, np.int64)
    for layer in range(num_layers):
        start[layer + 1] = start[layer] + counts[layer]
    pos = start[:num_layers].copy()
    xyz = np.empty((n, 3), np.float32)
    rgb = np.empty((n, 3), np.uint8)
    for v in range(H):
        for u in range(W):
            d = depth[v, u]
            if not (np.isfinite(d) and d > 0):
                continue
            z = np.float64(d)
            layer = 0
            if span > 0:
                layer = min(np.int64((z - lo) / span * num_layers), num_layers - 1)
            x = (np.float64(u) - cx) / fx * z
            y = (np.float64(v) - cy) / fy * z
            i = pos[layer]
            pos[layer] = i + 1
            for k in range(3):
                xyz[i, k] = np.float32(x * T[k, 0] + y * T[k, 1] + z * T[k, 2] + T[k, 3])
                rgb[i, k] = color[v, u, k]
    return xyz, rgb, start, lo, hi


def prepare_view(color: np.ndarray, depth_m: np.ndarray, K: Intrinsics, T_world_cam: np.ndarray,
                 num_layers: int) -> ViewPoints:
    """Back-project the valid pixels of one RGB-D view, assign layers and sort by layer (numba, one
    pass per step; :func:`prepare_view_ref` is the numpy reference, tested equal).

    Args:
        color: uint8 (h, w, 3); depth_m: float32 (h, w), 0 = invalid; K: the view's intrinsics.
        T_world_cam: 4x4 pose of the view.
    """
    if color.shape != (K.height, K.width, 3) or color.dtype != np.uint8:
        raise ValueError(f"color must be uint8 {K.height}x{K.width}x3, got {color.dtype} {color.shape}")
    depth = np.asarray(depth_m)
    if depth.shape != (K.height, K.width):
        raise ValueError(f"depth shape {depth.shape} != intrinsics {K.height}x{K.width}")
    if num_layers < 1:
        raise ValueError(f"num_layers must be >= 1, got {num_layers}")
    xyz, rgb, start, lo, hi = _prepare_kernel(
        np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(color), float(K.fx), float(K.fy),
        float(K.cx), float(K.cy), np.ascontiguousarray(np.asarray(T_world_cam, np.float64)), int(num_layers))
    rng = (float(lo), float(hi)) if len(xyz) else (0.0, 0.0)
    return ViewPoints(xyz, rgb, start, rng)


# fastmath without "nnan"/"ninf": the kernel relies on comparisons that must stay IEEE-exact.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@nb.njit(cache=True, nogil=True)
def _layer_slots_kernel(layer_start, n_slots):  # pragma: no cover
    L = layer_start.shape[0] - 1
    counts = np.empty(L, np.int64)
    for l in range(L):
        counts[l] = layer_start[l + 1] - layer_start[l]
    by_size = np.argsort(-counts, kind="mergesort")  # largest first, ties by layer index
    slot_of = np.empty(L, np.int64)
    load = np.zeros(n_slots, np.int64)
    size = np.zeros(n_slots, np.int64)
    for l in by_size:
        s = 0
        for j in range(1, n_slots):
            if load[j] < load[s]:
                s = j
        slot_of[l] = s
        load[s] += counts[l]
        size[s] += 1
    slot_start = np.zeros(n_slots + 1, np.int64)
    for s in range(n_slots):
        slot_start[s + 1] = slot_start[s] + size[s]
    pos = slot_start[:n_slots].copy()
    order = np.empty(L, np.int64)
    for l in by_size:
        order[pos[slot_of[l]]] = l
        pos[slot_of[l]] += 1
    return order, slot_start


def layer_slots(layer_start: np.ndarray, n_slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Layers grouped into ``n_slots`` groups of similar point counts (largest layer first, each
    to the lightest group; ties to the lower index), for a parallel loop that gives every thread
    one group.

    Returns:
        ``(order, slot_start)``: int64 layer indices grouped by slot; slot ``s`` holds
        ``order[slot_start[s]:slot_start[s + 1]]`` (at most one slot per layer).
    """
    ls = np.ascontiguousarray(layer_start, np.int64)
    return _layer_slots_kernel(ls, max(1, min(int(n_slots), ls.shape[0] - 1)))


@nb.njit(cache=True, nogil=True)
def _frustum_planes(M, fx, fy, cx, cy, near, W, H):  # pragma: no cover
    # The warp kernel's keep tests as 5 linear functions of the world point, g_k(p) = G_k . (p, 1)
    # >= 0 (float64, from the kernel's float32 M and intrinsics): z > near, u >= 0, u < W, v >= 0,
    # v < H, with u = fx x / z + cx + 0.5 multiplied out by z > 0; and E: the same functions with
    # absolute coefficients (a bound of each term's magnitude, for the rounding margin).
    G = np.empty((5, 4))
    E = np.empty((5, 4))
    for j in range(4):
        r0 = np.float64(M[0, j])
        r1 = np.float64(M[1, j])
        r2 = np.float64(M[2, j])
        nz = near if j == 3 else 0.0
        G[0, j] = r2 - nz
        G[1, j] = fx * r0 + (cx + 0.5) * r2
        G[2, j] = (W - cx - 0.5) * r2 - fx * r0
        G[3, j] = fy * r1 + (cy + 0.5) * r2
        G[4, j] = (H - cy - 0.5) * r2 - fy * r1
        E[0, j] = abs(r2) + abs(nz)
        E[1, j] = fx * abs(r0) + (abs(cx) + 0.5 + W) * abs(r2)
        E[2, j] = E[1, j]
        E[3, j] = fy * abs(r1) + (abs(cy) + 0.5 + H) * abs(r2)
        E[4, j] = E[3, j]
    return G, E


@nb.njit(cache=True, nogil=True)
def _chunk_visibility_kernel(lo, hi, M, fx, fy, cx, cy, near, W, H, margin_rel, vis):  # pragma: no cover
    # A chunk is culled when, for one of the frustum's half-spaces g_k(p) >= 0, even the box's
    # maximum of g_k is below -margin_rel x (a bound of g_k's magnitude: E_k on the box's largest
    # |coordinates|): every point of the chunk is then dropped by the warp kernel's float32 tests
    # too (their rounding is ~1e-6 of that bound). Boxes with a non-finite bound are kept.
    G, E = _frustum_planes(M, fx, fy, cx, cy, near, W, H)
    m = lo.shape[0]
    n_vis = 0
    for c in range(m):
        keep = np.uint8(1)
        finite = True
        for j in range(3):
            if not (np.isfinite(lo[c, j]) and np.isfinite(hi[c, j])):
                finite = False
        if finite:
            for k in range(5):
                g = G[k, 3]
                e = E[k, 3]
                for j in range(3):
                    a = G[k, j]
                    lj = np.float64(lo[c, j])
                    hj = np.float64(hi[c, j])
                    g += a * lj if a * lj > a * hj else a * hj
                    e += E[k, j] * max(abs(lj), abs(hj))
                if g < -margin_rel * e:
                    keep = np.uint8(0)
                    break
        vis[c] = keep
        n_vis += np.int64(keep)
    return n_vis


_NO_TILES = np.zeros((1, 1), np.uint8)
_CULL_MARGIN = 1e-4  # relative: ~100x the float32 rounding of the kernel's projection


def _visibility(view: ViewPoints, M32: np.ndarray, K: Intrinsics, near_m: float) -> np.ndarray:
    vis = np.ones(view.chunk_lo.shape[0], np.uint8)
    if near_m > 0:
        _chunk_visibility_kernel(view.chunk_lo, view.chunk_hi, M32, float(np.float32(K.fx)), float(np.float32(K.fy)),
                                 float(np.float32(K.cx)), float(np.float32(K.cy)), float(np.float32(near_m)),
                                 K.width, K.height, _CULL_MARGIN, vis)
    return vis


def chunk_visibility(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, near_m: float = 1e-3
                     ) -> np.ndarray:
    """uint8 (n_chunks,): 0 where every point of the chunk certainly falls outside the target
    camera (behind its near plane or outside the image), so :func:`warp_layers` can skip it
    without projecting; 1 otherwise (conservative: a 1 may still drop all its points). With
    ``near_m`` <= 0 nothing is culled."""
    M = np.ascontiguousarray(np.asarray(T_cam_world, np.float64)[:3, :4], np.float32)
    return _visibility(view, M, K, near_m)


@parallel_kernel(fastmath=_FASTMATH, cache=True)
def _warp_layers_kernel(xyz, rgb, layer_start, n_threads, M, fx, fy, cx, cy, near, pix, zs, tiles, use_tiles, tile_px,
                        tile_of_px, vis, chunk, zbuf, cbuf):  # pragma: no cover
    # Per layer: clear its buffers (with tiles, only the marked tiles: the rest is left as it was),
    # project its points (a loop without stores that depend on other points: it vectorizes), then
    # z-buffer them in their (source) order. Splitting the projection from the z-buffer halved
    # the CPU time of one loop doing both (docs/synthesis.md).
    L, H, W = zbuf.shape
    th, tw = tiles.shape
    # (the thread count comes in as an argument: nb.get_num_threads() in here makes the kernel uncacheable)
    order, slot_start = _layer_slots_kernel(layer_start, max(1, min(n_threads, L)))
    # One slot (a group of layers of similar total point count) per thread: the layers of a
    # capture hold very different numbers of points (apc: ~50 k, 40 k, 10 k, 3 k), and equal
    # chunks of the layer range would leave one thread with most of them.
    for s in nb.prange(slot_start.shape[0] - 1):
        for j in range(slot_start[s], slot_start[s + 1]):
            l = order[j]
            zf = zbuf[l].reshape(H * W)
            cf = cbuf[l].reshape(H * W, 3)
            # Clear this layer (buffers are reused across calls: cheaper than fresh zero pages).
            if use_tiles:
                for ty in range(th):
                    for tx in range(tw):
                        if tiles[ty, tx]:
                            ya = ty * tile_px
                            xa = tx * tile_px
                            xb = min(xa + tile_px, W)
                            zbuf[l, ya:ya + tile_px, xa:xb] = 0.0
                            cbuf[l, ya:ya + tile_px, xa:xb] = 0
            else:
                zf[:] = 0.0
                cf[:] = 0
            i0 = layer_start[l]
            i1 = layer_start[l + 1]
            if i1 <= i0:
                continue
            # Chunks of points (vis = 0: all certainly outside the target, not projected).
            c0 = i0 // chunk
            c1 = (i1 - 1) // chunk + 1
            for ch in range(c0, c1):
                if vis[ch] == 0:
                    continue
                for i in range(max(i0, ch * chunk), min(i1, ch * chunk + chunk)):
                    # target pixel (flat v * W + u, -1 = dropped) and depth
                    x = xyz[i, 0]
                    y = xyz[i, 1]
                    z = xyz[i, 2]
                    zc = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
                    xc = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]
                    yc = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]
                    uf = fx * xc / zc + cx + np.float32(0.5)
                    vf = fy * yc / zc + cy + np.float32(0.5)
                    zs[i] = zc
                    # Bounds in float before the int cast (large values would overflow).
                    ok = zc > near and uf >= 0.0 and uf < W and vf >= 0.0 and vf < H
                    pix[i] = np.int64(vf) * W + np.int64(uf) if ok else -1
            for ch in range(c0, c1):
                if vis[ch] == 0:
                    continue
                for i in range(max(i0, ch * chunk), min(i1, ch * chunk + chunk)):
                    p = pix[i]
                    if p < 0:
                        continue
                    if use_tiles and tile_of_px[p] == 0:
                        continue
                    zc = zs[i]
                    cur = zf[p]
                    if cur == 0.0 or zc < cur:
                        zf[p] = zc
                        cf[p, 0] = rgb[i, 0]
                        cf[p, 1] = rgb[i, 1]
                        cf[p, 2] = rgb[i, 2]


def warp_layers(view: ViewPoints, T_cam_world: np.ndarray, K: Intrinsics, near_m: float = 1e-3,
                out: LayeredImage | None = None, tiles: np.ndarray | None = None,
                tile_px: int = 16, cull: bool = True) -> LayeredImage:
    """Warp a prepared view into the target camera, one z-buffered image per layer (numba).

    Args:
        view: from :func:`prepare_view`.
        T_cam_world: 4x4 world-to-target-camera transform (``invert(T_world_cam)``).
        K: target intrinsics (any size).
        near_m: points closer than this to the target camera are dropped.
        out: buffers of shape (L, H, W) / (L, H, W, 3) to overwrite (the Renderer reuses them);
            new ones are allocated when None or of another shape.
        tiles: optional uint8 (ceil(H / tile_px), ceil(W / tile_px)): warp only into the marked
            tiles of ``tile_px`` x ``tile_px`` pixels: points landing elsewhere are skipped and only
            the marked tiles are cleared, so the layers are UNDEFINED outside them and exactly
            what a full warp gives inside (:func:`presim.synthesis.composite.warp_tiles` marks
            what a later view's crack pass reads).
        cull: skip the chunks of points that :func:`chunk_visibility` proves fall outside the
            target (same output; False projects every point, for tests and benchmarks).
    Returns:
        LayeredImage with depth 0 / color 0 where a layer received no point.
    """
    L = view.num_layers
    if out is None or out.depth_m.shape != (L, K.height, K.width):
        out = LayeredImage(np.empty((L, K.height, K.width), np.float32),
                           np.empty((L, K.height, K.width, 3), np.uint8))
    n = view.xyz_world.shape[0]
    if out.pix is None or out.pix.shape[0] < n:  # per-point scratch, reused with the buffers
        out = LayeredImage(out.depth_m, out.color, np.empty(n, np.int64), np.empty(n, np.float32))
    M = np.ascontiguousarray(np.asarray(T_cam_world, np.float64)[:3, :4], np.float32)
    use = tiles is not None
    tile_of_px = _NO_TILES.reshape(-1)
    if use:
        want = (-(-K.height // tile_px), -(-K.width // tile_px))
        if tiles.shape != want or tiles.dtype != np.uint8:
            raise ValueError(f"warp_layers: tiles must be uint8 {want}, got {tiles.dtype} {tiles.shape}")
        # per pixel: its tile's flag (a byte load per point instead of two integer divisions)
        tile_of_px = np.ascontiguousarray(np.repeat(np.repeat(tiles, tile_px, 0)[:K.height], tile_px, 1)[:, :K.width])
        tile_of_px = tile_of_px.reshape(-1)
    if cull:
        vis = _visibility(view, M, K, near_m)
    else:
        vis = np.ones(view.chunk_lo.shape[0], np.uint8)
    _warp_layers_kernel(view.xyz_world, view.rgb, view.layer_start, nb.get_num_threads(), M, np.float32(K.fx),
                        np.float32(K.fy), np.float32(K.cx), np.float32(K.cy), np.float32(near_m), out.pix, out.z,
                        tiles if use else _NO_TILES, use, int(tile_px), tile_of_px, vis, CHUNK_PTS, out.depth_m,
                        out.color)
    return out
