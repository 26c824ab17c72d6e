"""Per-frame projection of the views' sub-sampled grids into the target camera, once per frame.

Each candidate's grid (``RenderConfig.overlap_stride_px``) answers the overlap (selection; reference
:func:`presim.synthesis.select.view_overlap`), the target pixels and fill area (next view; references
:func:`grid_pixels`, :func:`fill_area_ref`, :func:`count_in_mask`) and the footprint ratio (level of detail;
reference :func:`presim.synthesis.lod.footprint_ratio`). :class:`FrameGrids` projects each grid once per frame
(reference :func:`project_grid_ref`), branch-free per coordinate so it vectorizes."""

from __future__ import annotations

import functools
from typing import Callable, Sequence

import numba as nb
import numpy as np

from presim.capture.reprojection import nearest_pixel
from presim.geometry import Intrinsics, project, transform_points
from presim.synthesis.lod import LodConfig, choose_level

__all__ = ["grid_pixels", "per_coordinate", "project_grid_ref", "count_in_mask", "fill_area_ref", "FrameGrids"]


def project_grid_ref(xyz_world: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``(pix, z)``: int64 (n,) flat pixel ``v * W + u`` by ``floor(u + 0.5)`` of world points (n, 3) in a target
    camera, -1 behind it or outside; float32 (n,) target z. Reference of :meth:`FrameGrids.projection` (numpy)."""
    p = transform_points(T_cam_world, np.asarray(xyz_world, np.float32))
    uv, z = project(K, p)
    u, v, inb = nearest_pixel(uv, K.width, K.height)
    pix = np.where(inb, v * K.width + u, -1).astype(np.int64)
    return pix, np.asarray(z, np.float32)


def grid_pixels(grid_xyz_world: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics, near_m: float) -> np.ndarray:
    """Flat pixels (v * W + u) where a view's grid (m, 3) lands in the target, in front of ``near_m``."""
    if len(grid_xyz_world) == 0:
        return np.zeros(0, np.int64)
    uv, z = project(K, transform_points(T_cam_world, grid_xyz_world))
    ok = z > near_m
    u, v, inb = nearest_pixel(uv[ok], K.width, K.height)
    return v[inb] * K.width + u[inb]


def per_coordinate(xyz_world: np.ndarray) -> np.ndarray:
    """World points (n, 3) as C-contiguous float32 (3, n), one row per coordinate; no copy for a float32
    F-ordered (n, 3) array (how the Renderer keeps its grids)."""
    return np.ascontiguousarray(np.asarray(xyz_world, np.float32).T)


@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _grid_pixel(P, i, M, fx, fy, cx, cy, W, H):  # pragma: no cover
    # Point i's (P: (3, n)) float32 target z and flat pixel (pixel-centre rule; -1 behind or outside).
    # Branch-free so the loop vectorizes; the reference's arithmetic, operation by operation.
    x = np.float64(P[0, i])
    y = np.float64(P[1, i])
    z = np.float64(P[2, i])
    zc = np.float32(x * M[2, 0] + y * M[2, 1] + z * M[2, 2] + M[2, 3])
    xc = np.float32(x * M[0, 0] + y * M[0, 1] + z * M[0, 2] + M[0, 3])
    yc = np.float32(x * M[1, 0] + y * M[1, 1] + z * M[1, 2] + M[1, 3])
    uf = np.floor(fx * np.float64(xc) / np.float64(zc) + cx + 0.5)
    vf = np.floor(fy * np.float64(yc) / np.float64(zc) + cy + 0.5)
    ok = (zc > 0.0) & (uf >= 0) & (uf < W) & (vf >= 0) & (vf < H)
    uf = uf if ok else 0.0  # no float -> int conversion of a value out of range
    vf = vf if ok else 0.0
    p = np.int64(vf) * W + np.int64(uf)
    return (p if ok else np.int64(-1)), zc


@nb.njit(cache=True, nogil=True, error_model="numpy")  # nogil: also run by the view cache's background thread
def _project_grid_kernel(P, M, fx, fy, cx, cy, W, H, pix, z_out):  # pragma: no cover
    for i in range(P.shape[1]):
        pix[i], z_out[i] = _grid_pixel(P, i, M, fx, fy, cx, cy, W, H)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _any_front_kernel(P, M, fx, fy, cx, cy, W, H, near):  # pragma: no cover
    # = _count_front_kernel(*projection, near) > 0, stopping at the first point that counts.
    for i in range(P.shape[1]):
        p, zc = _grid_pixel(P, i, M, fx, fy, cx, cy, W, H)
        if p >= 0 and zc > near:
            return True
    return False


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _ratio_counts_kernel(z_src, z_t, pix, near, taus, counts):  # pragma: no cover
    # counts[0]: grid points with both depths > near inside the target; counts[1 + k]: those whose float32 ratio
    # z_src / z_t is <= taus[k]. One branch-free pass per count: each vectorizes.
    for k in range(counts.shape[0]):
        t = taus[max(k - 1, 0)]
        c = 0
        for i in range(z_src.shape[0]):
            a = z_src[i]
            b = z_t[i]
            c += (a > near) & (b > near) & (pix[i] >= 0) & ((k == 0) | (np.float32(a / b) <= t))
        counts[k] = c


@functools.lru_cache(maxsize=256)
def _level_taus(q: np.float64, f_src_px: float, config: LodConfig) -> np.ndarray:
    """float32 (1 + levels,): 0, then for level k the largest float32 median whose footprint ratio (the arithmetic
    of :meth:`FrameGrids.footprint_ratio`, ``q`` = sqrt(fx fy) of the target) passes ``choose_level``'s test."""
    def passes(m: np.float32, k: int) -> bool:
        return bool((2 ** k) * float(np.float32(m) * q / f_src_px) <= config.max_footprint)

    taus = [np.float32(0.0)]
    up, down = np.float32(np.inf), np.float32(0.0)
    for k in range(1, config.levels + 1):
        t = np.float32(min(config.max_footprint / 2 ** k * f_src_px / q, np.finfo(np.float32).max))
        while t > 0 and not passes(t, k):
            t = np.nextafter(t, down)
        while np.isfinite(nxt := np.nextafter(t, up)) and passes(nxt, k):
            t = nxt
        taus.append(t)
    return np.array(taus, np.float32)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _count_front_kernel(pix, z, near):  # pragma: no cover
    # np.count_nonzero((pix >= 0) & (z > near)) (near float32, as numpy compares it with float32 z).
    n = 0
    for i in range(pix.shape[0]):
        n += (pix[i] >= 0) & (z[i] > near)
    return n


@nb.njit(cache=True, nogil=True, error_model="numpy")
def count_in_mask(mask_flat, px):  # pragma: no cover
    """``np.count_nonzero(mask_flat[px])`` (numba: no gathered copy)."""
    n = 0
    for i in range(px.shape[0]):
        n += mask_flat[px[i]] != 0
    return n


def fill_area_ref(mask_flat: np.ndarray, pix: np.ndarray, z_src: np.ndarray, z_t: np.ndarray, near_m: float) -> float:
    """Reference of the fill-area sum: ``sum((z_src / z_t)^2)`` over grid points inside the image, in front of
    both cameras, landing on ``mask_flat``."""
    near = np.float32(near_m)
    ok = (pix >= 0) & (z_src > near) & (z_t > near)
    ok[ok] &= np.asarray(mask_flat).reshape(-1)[pix[ok]] != 0
    return float(np.sum((z_src[ok].astype(np.float64) / z_t[ok].astype(np.float64)) ** 2))


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _next_view_kernel(mask_flat, points, near, scale, use_need, need, frac, counts, sums):  # pragma: no cover
    # Per view k (points [starts[k], ends[k])): counts[k] = count_in_mask of its front pixels, sums[k] = the
    # fill-area sum; a view counts when sums[k] * scale[k] >= need (with use_need); the first whose count
    # reaches frac x the largest wins, -1 if none counts.
    pix, z_t, z_src, starts, ends = points
    for k in range(starts.shape[0]):
        n = 0
        s = 0.0
        for i in range(starts[k], ends[k]):
            p = pix[i]
            if p >= 0 and z_t[i] > near and mask_flat[p] != 0:
                n += 1
                if z_src[i] > near:
                    r = np.float64(z_src[i]) / np.float64(z_t[i])
                    s += r * r
        counts[k] = n
        sums[k] = s
    cmax = 0
    for k in range(counts.shape[0]):
        if counts[k] > 0 and use_need and not sums[k] * scale[k] >= need:
            counts[k] = 0
        cmax = max(cmax, counts[k])
    if cmax == 0:
        return -1
    for k in range(counts.shape[0]):
        if counts[k] > 0 and counts[k] >= frac * cmax:
            return k
    return -1


def _flat_f32(parts: list[np.ndarray], n: int) -> np.ndarray:
    """The arrays of ``parts`` end to end in one float32 (n,) array."""
    out = np.concatenate(parts).astype(np.float32, copy=False) if parts else np.zeros(0, np.float32)
    if len(out) != n:
        raise ValueError(f"source depths: {len(out)} values for {n} grid points")
    return out


def _mask_u8(mask_flat: np.ndarray) -> np.ndarray:
    """A bool or uint8 mask as uint8 (a view)."""
    return mask_flat.view(np.uint8) if mask_flat.dtype == np.bool_ else mask_flat


class FrameGrids:
    """The views' grids projected into one target camera (``T_cam_world`` 4x4, ``K``), each view at most once;
    ``grid_points(id)`` -> (m, 3) float32 world grid of view ``id`` (cached by the caller)."""

    def __init__(self, T_cam_world: np.ndarray, K: Intrinsics, grid_points: Callable[[int], np.ndarray]):
        self.T_cam_world, self.K = T_cam_world, K
        self._grid_points = grid_points
        self._proj: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # Each project() call fills one buffer: view -> (buffer, start, end); buffer -> views, source depths.
        self._where: dict[int, tuple[int, int, int]] = {}
        self._bufs: list[tuple[np.ndarray, np.ndarray, list[int]]] = []
        self._zsrc_of_buf: dict[int, np.ndarray] = {}
        self._args: tuple | None = None
        self._scales: dict[tuple[int, float], float] = {}

    def project(self, ids: Sequence[int]) -> None:
        """Project the grids of the views ``ids`` not projected yet, all in one kernel call."""
        missing = [int(v) for v in ids if int(v) not in self._proj]
        if not missing:
            return
        grids = [per_coordinate(self._grid_points(v)) for v in missing]
        n = sum(g.shape[1] for g in grids)
        pix = np.empty(n, np.int64)
        z = np.empty(n, np.float32)
        args = self._kernel_args()
        o = 0
        b = len(self._bufs)
        self._bufs.append((pix, z, missing))
        for v, g in zip(missing, grids):  # each grid straight into its slice of one output (no copy of the inputs)
            m = g.shape[1]
            p, zz = pix[o:o + m], z[o:o + m]
            if m:
                _project_grid_kernel(g, *args, p, zz)
            self._proj[v] = (p, zz)
            self._where[v] = (b, o, o + m)
            o += m

    def _kernel_args(self) -> tuple:
        """The projection kernels' camera arguments (``M`` = the 3x4 of ``T_cam_world``, float64)."""
        if self._args is None:
            K = self.K
            M = np.ascontiguousarray(np.asarray(self.T_cam_world, np.float64)[:3, :4])
            self._args = (M, float(K.fx), float(K.fy), float(K.cx), float(K.cy), int(K.width), int(K.height))
        return self._args

    def overlapping(self, ids: Sequence[int], near_m: float = 1e-3) -> np.ndarray:
        """bool (k,): :meth:`overlaps` > 0, stopping at the first grid point inside for unprojected views."""
        near = np.float32(near_m)
        out = np.zeros(len(ids), bool)
        for i, v in enumerate(ids):
            got = self._proj.get(int(v))
            if got is not None:
                out[i] = _count_front_kernel(got[0], got[1], near) > 0
                continue
            g = per_coordinate(self._grid_points(int(v)))
            out[i] = g.shape[1] > 0 and _any_front_kernel(g, *self._kernel_args(), near)
        return out

    def projection(self, v: int) -> tuple[np.ndarray, np.ndarray]:
        """``(pix, z)`` of view ``v``'s grid (see :func:`project_grid_ref`)."""
        v = int(v)
        if v not in self._proj:
            self.project([v])
        return self._proj[v]

    def overlaps(self, ids: Sequence[int], near_m: float = 1e-3) -> np.ndarray:
        """(k,) overlap of each view = :func:`presim.synthesis.select.view_overlap`."""
        self.project(ids)
        out = np.zeros(len(ids))
        near = np.float32(near_m)
        for i, v in enumerate(ids):
            pix, z = self._proj[int(v)]
            if len(pix):
                out[i] = _count_front_kernel(pix, z, near) / len(pix)
        return out

    def footprint_ratio(self, v: int, z_src: np.ndarray, f_src_px: float, near_m: float) -> float:
        """= :func:`presim.synthesis.lod.footprint_ratio` (with ``K_tgt``) from the view's source depths ``z_src``: the
        median of the float32 ratios (an even count halves the float32 sum of the middle two)."""
        pix, z_t = self.projection(v)
        near = np.float32(near_m)
        z_src = np.asarray(z_src, np.float32)
        ok = (z_src > near) & (z_t > near) & (pix >= 0)
        r = z_src[ok] / z_t[ok]
        if len(r) == 0:  # no grid point in front of both cameras and inside the target image
            return float("nan")
        h = len(r) // 2
        r = np.partition(r, [h - 1, h] if h else [h])
        med = r[h] if len(r) % 2 else np.float32(r[h - 1] + r[h]) / np.float32(2.0)
        return float(np.float32(med) * np.sqrt(self.K.fx * self.K.fy) / f_src_px)

    def lod_level(self, v: int, z_src: np.ndarray, f_src_px: float, near_m: float, config: LodConfig) -> int:
        """= :func:`~presim.synthesis.lod.choose_level` of :meth:`footprint_ratio` (0 without levels), decided by
        counting the ratios under each level's threshold (7 vs 30 us per 4 800-point grid); the median is taken only
        when a threshold lies between the two middle ratios of an even count."""
        if config.levels == 0:
            return 0
        pix, z_t = self.projection(v)
        taus = _level_taus(np.sqrt(self.K.fx * self.K.fy), float(f_src_px), config)
        counts = np.empty(len(taus) + 1, np.int64)
        _ratio_counts_kernel(np.ascontiguousarray(z_src, np.float32), z_t, pix, np.float32(near_m), taus, counts)
        m, half = int(counts[0]), int(counts[0]) // 2
        if m == 0:
            return 0
        for k in range(len(taus)):
            if m % 2 == 0 and counts[k + 1] == half:  # the median could lie either side: compute it
                return choose_level(self.footprint_ratio(v, z_src, f_src_px, near_m), config)
            below = counts[k + 1] > half  # the median is <= taus[k]
            if k == 0 and below:  # a median <= 0 is level 0
                return 0
            if k > 0 and not below:
                return k - 1
        return len(taus) - 1

    def next_view(self, ids: Sequence[int], mask_flat: np.ndarray, z_src: Callable[[int], np.ndarray],
                  f_src_px: Callable[[int], float], near_m: float, stride_px: float, need: float | None,
                  frac: float) -> int:
        """The adaptive loop's next view in one kernel call: index in ``ids`` of the first view whose count of grid
        pixels on ``mask_flat`` reaches ``frac`` x the largest, counting only views whose fill area reaches ``need``
        (None: all): the target pixels its grid points on ``mask_flat`` stand for, each ``(stride_px x z_src / z_t x
        f_t / f_src)^2``; -1 if none. References: :func:`count_in_mask` of :func:`grid_pixels`,
        :func:`fill_area_ref`."""
        ids = [int(v) for v in ids]
        if not ids:
            return -1
        counts = np.empty(len(ids), np.int64)
        sums = np.empty(len(ids), np.float64)
        points = self._score_points(ids, z_src)  # (projects the views not projected yet)
        scale = np.array(self._fill_scales(ids, f_src_px, stride_px), np.float64)
        return int(_next_view_kernel(_mask_u8(mask_flat), points, np.float32(near_m), scale,
                                     need is not None, float(need) if need is not None else 0.0, float(frac),
                                     counts, sums))

    def _score_points(self, ids: list[int], z_src: Callable[[int], np.ndarray]) -> tuple:
        """``(pix, z_t, z_src, starts, ends)`` of views ``ids``; view k's points are ``[starts[k], ends[k])``."""
        self.project(ids)
        where = [self._where[v] for v in ids]
        b = where[0][0]
        if all(w[0] == b for w in where):  # the usual case: one buffer, flat, no copy
            pix, z_t, views = self._bufs[b]
            zs = self._zsrc_of_buf.get(b)
            if zs is None:
                zs = self._zsrc_of_buf[b] = _flat_f32([z_src(v) for v in views], len(z_t))
            starts = np.array([w[1] for w in where], np.int64)
            ends = np.array([w[2] for w in where], np.int64)
        else:  # views projected in several calls: their pieces, gathered
            pix = np.concatenate([self._proj[v][0] for v in ids])
            z_t = np.concatenate([self._proj[v][1] for v in ids])
            zs = _flat_f32([z_src(v) for v in ids], len(z_t))
            ends = np.cumsum([len(self._proj[v][1]) for v in ids], dtype=np.int64)
            starts = ends - np.array([len(self._proj[v][1]) for v in ids], np.int64)
        return pix, z_t, zs, starts, ends

    def _fill_scales(self, ids: list[int], f_src_px: Callable[[int], float], stride_px: float) -> list[float]:
        """Per view ``(stride_px x f_t / f_src)^2`` (0 for an empty grid), cached per view and stride."""
        out = []
        for v in ids:
            key = (v, stride_px)
            q = self._scales.get(key)
            if q is None:
                f_t = np.sqrt(self.K.fx * self.K.fy)
                q = self._scales[key] = float((stride_px * f_t / f_src_px(v)) ** 2) if len(self._proj[v][1]) else 0.0
            out.append(q)
        return out
