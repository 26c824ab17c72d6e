"""The per-frame grid projection (presim/synthesis/grids.py) against its numpy references."""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics, invert, look_at
from presim.synthesis.grids import (FrameGrids, count_in_mask, fill_area_ref, grid_pixels, per_coordinate,
                                    project_grid_ref)
from presim.synthesis.lod import choose_level, footprint_ratio
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.synthesis.select import view_overlap
from presim.testing import rect_scene as S


def _projection(pts, T_cam_world, K):
    return FrameGrids(T_cam_world, K, lambda v: pts).projection(0)


def test_project_grid_known_pixels():
    """Points on the optical axis and one pixel right of it, one behind the camera, one outside."""
    K = Intrinsics(100.0, 100.0, 3.5, 2.5, 8, 6)
    pts = np.array([[0.0, 0.0, 2.0],  # principal point (3.5, 2.5) -> floor(+0.5) = (4, 3)
                    [0.03, 0.0, 2.0],  # u = 1.5 + 3.5 = 5 -> floor(5.5) = 5
                    [0.0, 0.0, -1.0],  # behind
                    [1.0, 0.0, 1.0]], np.float32)  # u = 103.5: outside
    for pix, z in (_projection(pts, np.eye(4), K), project_grid_ref(pts, np.eye(4), K)):
        assert pix.tolist() == [3 * 8 + 4, 3 * 8 + 5, -1, -1]
        np.testing.assert_array_equal(z, [2.0, 2.0, -1.0, 1.0])
    assert _projection(np.zeros((0, 3), np.float32), np.eye(4), K)[0].shape == (0,)


def test_project_grid_matches_reference():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (20000, 3)).astype(np.float32)
    T = look_at([0.3, -0.2, -4.0], [0.0, 0.1, 0.0])
    K = Intrinsics.from_fov(160, 120, 70.0)
    a_pix, a_z = _projection(pts, invert(T), K)
    b_pix, b_z = project_grid_ref(pts, invert(T), K)
    np.testing.assert_array_equal(a_z, b_z)
    assert (a_pix == b_pix).mean() > 0.9995  # float64 summation order may move a boundary point
    assert (a_pix >= 0).sum() > 1000 and (a_pix == -1).sum() > 1000  # both branches exercised


def test_renderer_grids_are_stored_per_coordinate():
    """The kernels read the Renderer's grids per coordinate without a copy; other layouts are copied."""
    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(3, span_m=1.2), K)
    grid = Renderer(scene, RenderConfig(overlap_stride_px=4)).grid_points(1)
    P = per_coordinate(grid)
    assert P.shape == (3, len(grid)) and P.flags.c_contiguous and P.dtype == np.float32
    assert np.shares_memory(P, grid)
    np.testing.assert_array_equal(P.T, grid)
    C = np.ascontiguousarray(grid)
    assert not np.shares_memory(per_coordinate(C), C)
    np.testing.assert_array_equal(per_coordinate(C), P)


def test_frame_grids_answers_equal_the_reference_functions():
    """Overlap, hole-test pixels and LOD footprint from one projection = the per-question references."""
    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(6, span_m=1.2), K)
    r = Renderer(scene, RenderConfig(overlap_stride_px=4))
    T = scene.T_world_cam[2].copy()
    T[:3, 3] += [0.05, 0.0, 0.1]
    T_cw = invert(T)
    Kt = Intrinsics.from_fov(40, 30, 60.0)
    g = FrameGrids(T_cw, Kt, r.grid_points)
    ids = list(range(len(scene)))
    ov = g.overlaps(ids)
    for i, v in enumerate(ids):
        grid = r.grid_points(v)
        assert ov[i] == pytest.approx(view_overlap(grid, T_cw, Kt), abs=1e-9)
        np.testing.assert_array_equal(_front_pixels(g, v, 0.01), grid_pixels(grid, T_cw, Kt, 0.01))
        ref = footprint_ratio(grid, invert(scene.T_world_cam[v]), float(r.src_focal[v]), T_cw,
                              float(np.sqrt(Kt.fx * Kt.fy)), 0.01, Kt)
        ref_near = footprint_ratio(grid, invert(scene.T_world_cam[v]), float(r.src_focal[v]), T_cw,
                                   float(np.sqrt(Kt.fx * Kt.fy)), r.config.near_m, Kt)
        got_level = g.lod_level(v, r.grid_zsrc(v), float(r.src_focal[v]), r.config.near_m, r.lod)
        assert got_level == choose_level(ref_near, r.lod)
        got = g.footprint_ratio(v, r.grid_zsrc(v), float(r.src_focal[v]), 0.01)
        assert got == pytest.approx(ref, rel=1e-6)
    assert 0.3 < ov.max() <= 1.0


def _rss_of_map_kb(path) -> int:
    """Rss (kB) of the mappings of ``path`` in this process (/proc/self/smaps)."""
    total, hit = 0, False
    for line in open("/proc/self/smaps"):
        if "-" in line.split()[0] and len(line.split()) >= 5:
            hit = line.rstrip().endswith(str(path))
        elif hit and line.startswith("Rss:"):
            total += int(line.split()[1])
    return total


def test_unmap_pages_drops_a_read_only_memmap_slice_and_keeps_its_data(tmp_path):
    from presim.capture.store import unmap_pages

    path = tmp_path / "a.npy"
    a = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(8, 256, 256))
    a[:] = np.arange(8, dtype=np.float32)[:, None, None]
    a.flush()
    del a
    m = np.load(path, mmap_mode="r")
    frame = np.asarray(m[3])  # what ArrayFrameSource.load returns: a plain view of the map
    assert float(frame.sum()) == 3.0 * 256 * 256
    before = _rss_of_map_kb(path)
    unmap_pages(frame)
    after = _rss_of_map_kb(path)
    assert before >= 256 and after <= before - 200  # the frame's 256 kB left this process's RSS
    assert float(frame.sum()) == 3.0 * 256 * 256  # read again from the page cache
    w = np.ones((4, 4), np.float32)
    unmap_pages(w)  # in-memory / writable arrays: untouched
    assert w.sum() == 16


def _front_pixels(g, v, near_m):
    """The target pixels of view v's grid points in front of near_m (= grid_pixels, on the kernel's projection)."""
    pix, z = g.projection(v)
    return pix[(pix >= 0) & (z > np.float32(near_m))]


def _fill_area(r, g, v, mask_flat, near_m):
    """A view's fill area: its grid points on the mask, each (stride x z_src / z_t x f_t / f_src)^2 target pixels
    (fill_area_ref's terms, summed in point order as the kernel does: a need set to one view's area is exact)."""
    pix, z_t = g.projection(v)
    zs = r.grid_zsrc(v)
    near = np.float32(near_m)
    ok = (pix >= 0) & (zs > near) & (z_t > near)
    ok[ok] &= np.asarray(mask_flat).reshape(-1)[pix[ok]] != 0
    terms = (zs[ok].astype(np.float64) / z_t[ok].astype(np.float64)) ** 2
    total = float(np.cumsum(terms)[-1]) if len(terms) else 0.0
    assert total == pytest.approx(fill_area_ref(mask_flat, pix, zs, z_t, near_m), rel=1e-12)
    return total * (r.config.overlap_stride_px * np.sqrt(g.K.fx * g.K.fy) / r.src_focal[v]) ** 2


def test_fill_area_known_answers():
    """Each grid point landing on the mask stands for (stride x z_src / z_t x f_t / f_src)^2 target
    pixels: a target at a view's own pose sees its stride-8 grid as 64 px per point; a target with
    half the focal length as 16 px; only masked points count. next_view's kernel gates on the same area."""
    scene = S.make_scene(S.room_rects(), S.orbit_poses(3, span_m=0.6), Intrinsics.from_fov(96, 72, 60.0))
    r = Renderer(scene, RenderConfig())
    K = scene.intrinsics[1]
    near = r.config.near_m

    def check(g, mask, want):
        assert _fill_area(r, g, 1, mask, near) == pytest.approx(want, rel=1e-5)
        for need, got in ((want * (1 - 1e-4), 0), (want * (1 + 1e-4), -1)):
            assert g.next_view([1], mask, r.grid_zsrc, lambda v: float(r.src_focal[v]), near,
                               float(r.config.overlap_stride_px), need, 0.0) == got

    grids = FrameGrids(invert(scene.T_world_cam[1]), K, r.grid_points)
    n_in = int((grids.projection(1)[0] >= 0).sum())
    assert n_in > 50
    check(grids, np.ones(K.width * K.height, np.uint8), 64.0 * n_in)
    half = K.scaled(K.width // 2, K.height // 2)
    g2 = FrameGrids(invert(scene.T_world_cam[1]), half, r.grid_points)
    check(g2, np.ones(half.width * half.height, bool), 16.0 * int((g2.projection(1)[0] >= 0).sum()))
    top = np.zeros((K.height, K.width), np.uint8)
    top[:K.height // 2] = 1  # only the points landing in the top half count
    pix = grids.projection(1)[0]
    check(grids, top.reshape(-1), 64.0 * int(((pix >= 0) & (pix < (K.height // 2) * K.width)).sum()))


def test_next_view_is_the_loops_rule_on_the_per_candidate_counts_and_fill_areas():
    """FrameGrids.next_view (all pending candidates in one kernel call) = the adaptive loop's rule on the
    references: count_in_mask of each view's target pixels and its fill area (fill_area_ref): the first view
    whose count reaches ``frac`` x the largest, counting only views whose fill area reaches ``need``; views
    projected in separate calls or all in one, views with no point in the image and bool / uint8 masks."""
    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(8, span_m=1.6), K)
    r = Renderer(scene, RenderConfig(overlap_stride_px=4))
    near = r.config.near_m
    stride = float(r.config.overlap_stride_px)
    T = look_at(np.array([0.3, -0.2, 0.1]), np.array([0.0, 0.0, 2.0]))
    Kt = Intrinsics.from_fov(40, 30, 70.0)
    rng = np.random.default_rng(5)
    checked = nexts = 0
    cams = (invert(T), invert(scene.T_world_cam[3]), invert(T @ look_at(np.zeros(3), np.array([0.0, 0.0, -1.0]))))
    for T_cam_world, earlier in zip(cams * 2, [[0, 1]] * 3 + [[]] * 3):
        grids = FrameGrids(T_cam_world, Kt, r.grid_points)
        grids.project(earlier)  # some views projected earlier, in another call (or all in one)
        for frac in (0.0, 0.3, 1.0):
            for dtype in (np.uint8, bool):
                mask = (rng.random(Kt.width * Kt.height) < frac).astype(dtype)
                ids = [5, 0, 7, 2, 1]
                for near_m in (near, 1.2):  # 1.2 m: drops part of the grids (in the image, too near)
                    counts = [count_in_mask(mask.view(np.uint8), _front_pixels(grids, v, near_m)) for v in ids]
                    fills = [_fill_area(r, grids, v, mask, near_m) for v in ids]
                    checked += sum(counts)
                    for need in (None, 0.0, float(np.median(fills)), max(fills) + 1.0):
                        for pick in (0.0, 0.5, 1.0):
                            gated = [n if n > 0 and (need is None or f >= need) else 0 for n, f in zip(counts, fills)]
                            want = -1 if max(gated) == 0 else next(
                                i for i, n in enumerate(gated) if n > 0 and n >= pick * max(gated))
                            got = grids.next_view(ids, mask, r.grid_zsrc, lambda v: float(r.src_focal[v]),
                                                  near_m, stride, need, pick)
                            assert got == want
                            nexts += want >= 0
    assert checked > 100 and nexts > 50
    empty = FrameGrids(invert(T), Kt, r.grid_points)
    assert empty.next_view([], np.ones(Kt.width * Kt.height, np.uint8), r.grid_zsrc, lambda v: 1.0, near, stride,
                           None, 0.0) == -1


def test_overlapping_equals_overlap_above_zero_and_selection_is_unchanged():
    """FrameGrids.overlapping (stops at the first point inside) = overlaps > 0, projected or not, and
    a selection with only max_views exact overlaps picks the same views in the same order."""
    from presim.synthesis.select import select_views

    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(12, span_m=1.6), K)
    r = Renderer(scene, RenderConfig(overlap_stride_px=4))
    ids = list(range(len(scene)))
    Kt = Intrinsics.from_fov(40, 30, 60.0)
    n_none = n_some = n_nan = 0
    for k, T in enumerate([look_at((x, -1.0, 1.25), (3.0 * x, y, 0.4)) for x in (-0.4, 0.0, 0.4)
                           for y in (0.5, -3.0)]):  # y = -3: looking away from most of the room
        T_cw = invert(T)
        want = FrameGrids(T_cw, Kt, r.grid_points).overlaps(ids) > 0
        g = FrameGrids(T_cw, Kt, r.grid_points)
        if k % 2:
            g.project(ids[:3])  # some views projected already: answered from their projection
        np.testing.assert_array_equal(g.overlapping(ids), want)
        n_none += int((~want).sum())
        n_some += int(want.sum())
        args = (T, Kt, r.centres, r.dirs, r.hfov_deg, r.grid_points)
        full = select_views(*args, overlaps=g.overlaps)
        for n_exact in (1, 2, 6):
            fast = select_views(*args, overlaps=g.overlaps, overlapping=g.overlapping, exact_overlaps=n_exact)
            np.testing.assert_array_equal(fast.view_idx, full.view_idx)
            m = min(n_exact, len(full.view_idx))
            np.testing.assert_array_equal(fast.overlap_frac[:m], full.overlap_frac[:m])
            assert np.isnan(fast.overlap_frac[m:]).all()
            n_nan += len(fast.overlap_frac) - m
        assert (select_views(*args, order="overlap", overlaps=g.overlaps, overlapping=g.overlapping,
                             exact_overlaps=1).overlap_frac > 0).all()  # overlap order: all computed
    assert n_none > 0 and n_some > 0 and n_nan > 0  # both answers and the nan tail exercised
