"""Fast paths (numba, torch on CPU) against the numpy reference, on small analytic scenes.

Tolerance: the reference projects in float64 via presim.geometry, the fast paths in float32 (numba
with fastmath re-association), so a point whose projection lies within ~1e-5 px of a pixel border can
land one pixel over, and two points within ~1e-7 m of each other in z can swap. Such flips happen
only at pixel borders / depth ties, so we allow at most 0.5 % differing pixels, and the crack filter /
composite (no arithmetic) must match exactly on identical inputs.
"""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics, invert, look_at, make_pose, transform_points
from presim.synthesis import kernels_reference as ref
from presim.testing import rect_scene as S
from presim.synthesis.cracks import crack_filter
from presim.testing.naive import naive_zbuffer
from presim.synthesis.warp import prepare_view, warp_layers

K_SMALL = Intrinsics.from_fov(96, 72, 60.0)


def _room_view(K=K_SMALL, L=4):
    T_src = look_at((0.0, -1.0, 1.3), (0.0, 0.5, 0.4))
    color, depth = S.raycast(S.room_rects(), T_src, K)
    vp = prepare_view(color, depth, K, T_src, L)
    T_tgt = look_at((0.15, -0.9, 1.25), (0.0, 0.5, 0.4))
    return vp, invert(T_tgt)


def _frac_diff(a, b):
    return float(np.mean(a != b)) if a.ndim == 2 else float(np.mean(np.any(a != b, axis=-1)))


def test_assign_layers_reference_is_the_per_point_rule():
    d = np.random.default_rng(0).uniform(0.3, 4.0, 5000)
    for L in (1, 2, 4, 8):
        lay, (lo, hi) = ref.assign_layers_ref(d, L)
        assert lo == d.min() and hi == d.max()
        np.testing.assert_array_equal(lay, [min(int((x - lo) / (hi - lo) * L), L - 1) for x in d])


@pytest.mark.parametrize("L", [1, 4])
def test_numba_warp_matches_reference(L):
    vp, T_cam_world = _room_view(L=L)
    dn = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
    dr, cr = ref.warp_layers_ref(vp.xyz_world, vp.rgb, vp.layer, L, T_cam_world, K_SMALL, 1e-3)
    assert (dr > 0).mean() > 0.1
    assert _frac_diff(dn.depth_m > 0, dr > 0) < 0.005
    both = (dn.depth_m > 0) & (dr > 0)
    assert np.abs(dn.depth_m[both] - dr[both]).max() < 1e-4 + 0.05  # a flipped pixel: neighbour's z
    assert _frac_diff(dn.color, cr) < 0.005


def _switching_median_per_pixel(depth_m, color, kernel_px):
    """Eq. 3.9 pixel by pixel: an empty pixel whose window (outside = empty) is more than half non-empty takes
    the lower median of the non-empty depths and of each colour channel."""
    H, W = depth_m.shape
    r = kernel_px // 2
    out_d, out_c = depth_m.copy(), color.copy()
    for v in range(H):
        for u in range(W):
            if depth_m[v, u] > 0:
                continue
            win = [(y, x) for y in range(v - r, v + r + 1) for x in range(u - r, u + r + 1)
                   if 0 <= y < H and 0 <= x < W and depth_m[y, x] > 0]
            if 2 * len(win) > kernel_px * kernel_px:
                k = (len(win) - 1) // 2
                out_d[v, u] = sorted(depth_m[y, x] for y, x in win)[k]
                out_c[v, u] = [sorted(color[y, x, ch] for y, x in win)[k] for ch in range(3)]
    return out_d, out_c


def _plain_median_per_pixel(depth_m, color, kernel_px):
    """Every pixel: the median of its zero-padded window; colour 0 where that depth is not > 0."""
    r, mid = kernel_px // 2, (kernel_px * kernel_px - 1) // 2
    pd, pc = np.pad(depth_m, r), np.pad(color, ((r, r), (r, r), (0, 0)))
    out_d, out_c = np.zeros_like(depth_m), np.zeros_like(color)
    for v in range(depth_m.shape[0]):
        for u in range(depth_m.shape[1]):
            out_d[v, u] = np.sort(pd[v:v + kernel_px, u:u + kernel_px].ravel())[mid]
            if out_d[v, u] > 0:
                out_c[v, u] = np.sort(pc[v:v + kernel_px, u:u + kernel_px].reshape(-1, 3), axis=0)[mid]
    return out_d, out_c


@pytest.mark.parametrize("mode,fn", [("switching_median", _switching_median_per_pixel),
                                     ("median", _plain_median_per_pixel)])
def test_crack_filter_reference_is_the_per_pixel_definition(mode, fn):
    """The vectorized reference (crack_filter) = the filter written pixel by pixel: random cracks of all
    densities, ties, NaN and negative depths, 255 colours, windows 1 / 3 / 5, layers and single images."""
    rng = np.random.default_rng(1)
    for trial in range(12):
        d = rng.uniform(0.5, 3.0, (2, int(rng.integers(1, 24)), int(rng.integers(1, 24)))).astype(np.float32)
        d[rng.random(d.shape) < rng.uniform(0.0, 1.0)] = 0
        d[rng.random(d.shape) < 0.1] = 2.0  # ties
        d[rng.random(d.shape) < 0.05] = np.nan if trial % 2 else -1.0
        c = rng.integers(0, 256, d.shape + (3,), dtype=np.uint8)
        c[rng.random(d.shape) < 0.2] = 255
        for kpx in (1, 3, 5):
            dn, cn = crack_filter(d, c, mode, kpx)
            for i in range(2):
                dr, cr = fn(d[i], c[i], kpx)
                np.testing.assert_array_equal(dn[i], dr)
                np.testing.assert_array_equal(cn[i], cr)
            d1, c1 = crack_filter(d[0], c[0], mode, kpx)
            np.testing.assert_array_equal(d1, dn[0])
            np.testing.assert_array_equal(c1, cn[0])


def test_composite_reference_is_the_per_pixel_definition():
    rng = np.random.default_rng(2)
    d = rng.uniform(0.5, 3.0, (4, 30, 40)).astype(np.float32)
    d[rng.random(d.shape) < 0.6] = 0
    d[rng.random(d.shape) < 0.05] = np.nan
    c = rng.integers(0, 256, d.shape + (3,), dtype=np.uint8)
    dr, cr = ref.composite_layers_ref(d, c)
    for v in range(d.shape[1]):
        for u in range(d.shape[2]):
            front = [lay for lay in range(d.shape[0]) if d[lay, v, u] > 0]
            assert dr[v, u] == (d[front[0], v, u] if front else 0.0)
            assert cr[v, u].tolist() == (c[front[0], v, u].tolist() if front else [0, 0, 0])


def test_torch_paths_match_reference_on_cpu():
    import torch
    from presim.synthesis import torch_kernels as tb

    vp, T_cam_world = _room_view(L=4)
    tv = tb.to_device(vp, "cpu")
    dt, ct = tb.warp_layers_torch(tv, T_cam_world, K_SMALL, 1e-3)
    dr, cr = ref.warp_layers_ref(vp.xyz_world, vp.rgb, vp.layer, 4, T_cam_world, K_SMALL, 1e-3)
    assert _frac_diff(dt.numpy() > 0, dr > 0) < 0.005
    assert _frac_diff(ct.numpy(), cr) < 0.005
    # Filters and composite have no arithmetic: exact on identical inputs.
    for mode, fn in (("switching_median", ref.switching_median_ref), ("median", ref.plain_median_ref)):
        fd, fc = tb.crack_filter_torch(torch.from_numpy(dr), torch.from_numpy(cr), mode, 3)
        for i in range(4):
            e_d, e_c = fn(dr[i], cr[i], 3)
            np.testing.assert_array_equal(fd[i].numpy(), e_d)
            np.testing.assert_array_equal(fc[i].numpy(), e_c)
    kd, kc = tb.composite_layers_torch(torch.from_numpy(dr), torch.from_numpy(cr))
    e_d, e_c = ref.composite_layers_ref(dr, cr)
    np.testing.assert_array_equal(kd.numpy(), e_d)
    np.testing.assert_array_equal(kc.numpy(), e_c)


def test_renderer_backends_agree():
    from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(4), K)
    T = look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4))
    outs = {b: Renderer(scene, RenderConfig(fill_holes=False), PerfConfig(backend=b)).render(T, K)
            for b in ("reference", "numba", "torch")}
    for b in ("numba", "torch"):
        assert _frac_diff(outs[b].valid, outs["reference"].valid) < 0.01, b
        assert _frac_diff(outs[b].color, outs["reference"].color) < 0.02, b
        assert _frac_diff(outs[b].source_view, outs["reference"].source_view) < 0.02, b


def test_naive_baseline_matches_single_layer_warp():
    """The benchmark's naive baseline is the same z-buffer as L=1 without filtering."""
    vp, T_cam_world = _room_view(L=1)
    T_src = look_at((0.0, -1.0, 1.3), (0.0, 0.5, 0.4))
    color, depth = S.raycast(S.room_rects(), T_src, K_SMALL)
    cb, db = naive_zbuffer([(color, depth, K_SMALL, T_src)], invert(T_cam_world), K_SMALL)
    dr, cr = ref.warp_layers_ref(vp.xyz_world, vp.rgb, vp.layer, 1, T_cam_world, K_SMALL, 1e-3)
    assert _frac_diff(db > 0, dr[0] > 0) < 0.005
    assert _frac_diff(cb, cr[0]) < 0.005


def _reference_view_chain(ld, lc):
    """Per-layer switching median -> front-to-back composite -> seam pass, all numpy reference."""
    pairs = [ref.switching_median_ref(ld[i], lc[i], 3) for i in range(ld.shape[0])]
    d, c = ref.composite_layers_ref(np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
    return ref.switching_median_ref(d, c, 3)


@pytest.mark.parametrize("L", [1, 4])
def test_prepare_view_numba_matches_reference(L):
    """One-pass numba view preparation = the numpy reference: same points (float32 rounding of the
    same float64 arithmetic), colours, layer split and order (stable within a layer)."""
    from presim.synthesis.kernels_reference import prepare_view_ref

    T_src = look_at((0.0, -1.0, 1.3), (0.0, 0.5, 0.4))
    color, depth = S.raycast(S.room_rects(), T_src, K_SMALL)
    depth = depth.copy()
    depth[::7, ::5] = 0.0  # invalid pixels
    depth[3, 4] = np.nan
    a = prepare_view(color, depth, K_SMALL, T_src, L)
    b = prepare_view_ref(color, depth, K_SMALL, T_src, L)
    np.testing.assert_array_equal(a.layer_start, b.layer_start)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert a.depth_range_m == b.depth_range_m
    np.testing.assert_allclose(a.xyz_world, b.xyz_world, rtol=0, atol=1e-6)
    assert a.xyz_world.dtype == np.float32 and len(a.xyz_world) == np.count_nonzero(depth > 0)
    empty = prepare_view(color, np.zeros_like(depth), K_SMALL, T_src, L)
    assert len(empty.xyz_world) == 0 and empty.depth_range_m == (0.0, 0.0) and empty.num_layers == L


def test_prepare_view_layers_at_the_layer_boundaries_match_the_reference():
    """Depths on and one float32 step beside every layer boundary (the numba kernel keeps each pixel's
    layer from its counting pass and takes the column / row divisions once): same layer split, same
    colours in the same order as the reference, and points within float32 rounding."""
    from presim.synthesis.kernels_reference import prepare_view_ref

    K = Intrinsics(40.0, 40.0, 11.5, 7.5, 24, 16)
    lo, hi, L = 1.0, 3.0, 4
    edges = [lo + (hi - lo) * k / L for k in range(L + 1)]
    vals = []
    for e in edges:
        e32 = np.float32(e)
        vals += [e32, np.nextafter(e32, np.float32(0)), np.nextafter(e32, np.float32(np.inf))]
    vals = np.clip(np.array(vals, np.float32), np.float32(lo), np.float32(hi))
    rng = np.random.default_rng(5)
    depth = rng.choice(vals, size=(16, 24)).astype(np.float32)
    depth[0, 0], depth[-1, -1] = lo, hi  # the range is exactly [lo, hi]
    depth[3, ::4] = 0.0
    depth[5, 7] = np.inf
    color = rng.integers(0, 256, (16, 24, 3), dtype=np.uint8)
    T = look_at((0.2, -1.0, 1.1), (0.0, 0.5, 0.4))
    a = prepare_view(color, depth, K, T, L)
    b = prepare_view_ref(color, depth, K, T, L)
    np.testing.assert_array_equal(a.layer_start, b.layer_start)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_allclose(a.xyz_world, b.xyz_world, rtol=0, atol=1e-6)
    assert (np.diff(a.layer_start) > 0).all()  # every layer met


@pytest.mark.parametrize("L,density,band", [(1, 0.6, 16), (2, 0.55, 3), (4, 0.35, 32), (8, 0.6, 1), (4, 0.5, 7)])
def test_banded_composite_matches_reference(L, density, band):
    """The row-band fusion of the crack pass = the numpy reference chain, bit for bit (all pixels;
    with a mask, the masked pixels), whatever the band height. Random sparse layers: many windows
    with exactly 4 / 5 neighbours (the switching threshold), per-channel medians that differ from
    the depth median's pixel, ties in depth."""
    from presim.synthesis.cracks import filtered_composite_banded

    rng = np.random.default_rng(10 + L)
    shape = (L, 37, 29)
    d = np.where(rng.random(shape) < density, rng.choice([0.5, 0.7, 1.0, 1.3], shape), 0).astype(np.float32)
    c = rng.integers(0, 256, shape + (3,), dtype=np.uint8) * (d > 0)[..., None].astype(np.uint8)
    rd, rc = _reference_view_chain(d, c)
    bd, bc = filtered_composite_banded(d, c, band_rows=band)
    np.testing.assert_array_equal(bd, rd)
    np.testing.assert_array_equal(bc, rc)
    mask = rng.random(shape[1:]) < 0.3
    md, mc = filtered_composite_banded(d, c, mask, band_rows=band)
    np.testing.assert_array_equal(md[mask], rd[mask])
    np.testing.assert_array_equal(mc[mask], rc[mask])


def test_banded_composite_takes_non_contiguous_layers():
    """The crack pass indexes the layers flat: strided views (a crop of bigger buffers) give the
    same output as contiguous copies of them (and as the reference chain)."""
    from presim.synthesis.cracks import filtered_composite_banded

    rng = np.random.default_rng(3)
    shape = (4, 41, 35)
    d = np.where(rng.random(shape) < 0.5, rng.choice([0.5, 0.7, 1.0, 1.3], shape), 0).astype(np.float32)
    c = rng.integers(0, 256, shape + (3,), dtype=np.uint8) * (d > 0)[..., None].astype(np.uint8)
    dv, cv = d[:, 2:39, 3:32], c[:, 2:39, 3:32]
    assert not dv.flags.c_contiguous
    rd, rc = _reference_view_chain(np.ascontiguousarray(dv), np.ascontiguousarray(cv))
    bd, bc = filtered_composite_banded(dv, cv, band_rows=8)
    np.testing.assert_array_equal(bd, rd)
    np.testing.assert_array_equal(bc, rc)


@pytest.mark.parametrize("band,tile_cols", [(32, 32), (5, 7), (1, 1), (8, 3)])
def test_tiled_crack_pass_and_masked_warp_match_reference(band, tile_cols):
    """Later views (a replace mask): the crack pass on runs of tiles holding masked pixels, over
    layers warped only into the tiles within 2 px of them (stale garbage elsewhere), equals the
    numpy reference chain over a full warp on every masked pixel, whatever the tile sizes."""
    from presim.imaging.masks import tile_any
    from presim.synthesis.cracks import filtered_composite_banded, warp_tiles

    vp, T_cam_world = _room_view(L=4)
    full = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
    rd, rc = _reference_view_chain(full.depth_m, full.color)
    rng = np.random.default_rng(band * 31 + tile_cols)
    H, W = K_SMALL.height, K_SMALL.width
    mask = np.zeros((H, W), bool)
    mask[rng.integers(0, H, 6), rng.integers(0, W, 6)] = True  # isolated pixels: most tiles stay off
    mask[H // 2:H // 2 + 9, 3:20] = rng.random((9, 17)) < 0.5
    for tile_px in (16, 5):
        tiles = warp_tiles(mask, tile_px)
        assert 0 < tiles.mean() < 1
        lay = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
        lay.depth_m[:] = 7.0  # stale values from an "earlier view" outside the tiles
        lay.color[:] = 200
        lay = warp_layers(vp, T_cam_world, K_SMALL, 1e-3, out=lay, tiles=tiles, tile_px=tile_px)
        on = np.repeat(np.repeat(tiles, tile_px, 0)[:H], tile_px, 1)[:, :W].astype(bool)
        np.testing.assert_array_equal(lay.depth_m[:, on], full.depth_m[:, on])  # tiles = a full warp
        np.testing.assert_array_equal(lay.color[:, on], full.color[:, on])
        assert (lay.depth_m[:, ~on] == 7.0).all()  # untouched outside
        md, mc = filtered_composite_banded(lay.depth_m, lay.color, mask, band_rows=band, tile_cols=tile_cols)
        np.testing.assert_array_equal(md[mask], rd[mask])
        np.testing.assert_array_equal(mc[mask], rc[mask])
    # tile_any known answer: one pixel at (5, 9), tiles 4x4, grown by 2 -> rows 3..7, cols 7..11
    m = np.zeros((12, 16), np.uint8)
    m[5, 9] = 1
    np.testing.assert_array_equal(tile_any(m, 4, 4, 2), [[0, 1, 1, 0], [0, 1, 1, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(tile_any(m, 4, 4, 0), [[0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]])
    with pytest.raises(ValueError, match="tiles must be uint8"):
        warp_layers(vp, T_cam_world, K_SMALL, 1e-3, tiles=np.ones((2, 2), np.uint8))


def test_large_frames_run_a_later_views_crack_pass_on_small_tiles(monkeypatch):
    """From TILED_MIN_PIXELS on, a replace mask of small scattered holes runs the crack pass on
    runs of TILE_ROWS x TILE_COLS tiles (work items no taller than TILE_ROWS, covering only a part
    of the image), with the same values on the replace pixels as the whole-band pass."""
    from presim.synthesis import cracks as CO

    rng = np.random.default_rng(11)
    L, H, W = 3, 400, 400
    assert H * W >= CO.TILED_MIN_PIXELS
    d = np.where(rng.random((L, H, W)) < 0.6, rng.choice([0.5, 0.8, 1.1], (L, H, W)), 0).astype(np.float32)
    c = rng.integers(0, 256, (L, H, W, 3), dtype=np.uint8)  # colour where the depth is 0 too: never read
    mask = np.zeros((H, W), bool)
    mask[rng.integers(0, H, 300), rng.integers(0, W, 300)] = True
    mask[100:106, 200:260] = True
    bd, bc = CO.filtered_composite_banded(d, c)  # whole bands, every pixel
    items = []
    tiled = CO.tiled_crack_kernel

    def record(*args):
        items.append(args[6].copy())
        return tiled(*args)

    monkeypatch.setattr(CO, "tiled_crack_kernel", record)
    md, mc = CO.filtered_composite_banded(d, c, mask)
    np.testing.assert_array_equal(md[mask], bd[mask])
    np.testing.assert_array_equal(mc[mask], bc[mask])
    assert len(items) == 1
    it = items[0]
    assert (it[:, 1] - it[:, 0]).max() <= CO.TILE_ROWS
    assert ((it[:, 1] - it[:, 0]) * (it[:, 3] - it[:, 2])).sum() < 0.5 * H * W
    covered = np.zeros((H, W), bool)
    for a, e, x0, x1 in it:
        covered[a:e, x0:x1] = True
    assert covered[mask].all()


def test_tile_any_matches_reference():
    """tile_any (ORs of 8-pixel words, rows zero-padded when the width is not a multiple of 8) = the
    dilate-then-block-any reference, for
    sparse, clustered and dense masks, tile sizes that do and do not divide the image, grow 0-5
    (wider than some tiles)."""
    from presim.imaging.masks import tile_any, tile_any_ref

    rng = np.random.default_rng(7)
    n = 0
    for H, W in ((1, 1), (7, 13), (48, 64), (61, 96), (5, 8), (33, 40)):  # W % 8 == 0: no padding
        for density in (0.0, 0.002, 0.05, 0.6, 1.0):
            m = (rng.random((H, W)) < density).astype(np.uint8)
            if density == 0.05:  # clusters: a block of set pixels
                m[H // 3:H // 3 + 4, W // 2:W // 2 + 5] = 1
            for th, tw in ((4, 4), (5, 7), (16, 32), (32, 3)):
                for grow in (0, 1, 2, 3, 5):
                    ref = tile_any_ref(m, th, tw, grow)
                    np.testing.assert_array_equal(tile_any(m, th, tw, grow), ref,
                                                  err_msg=f"{H}x{W} d={density} tile {th}x{tw} grow {grow}")
                    n += 1
    assert n == 6 * 5 * 4 * 5


def test_masked_warp_renders_identical_frames(monkeypatch):
    """The Renderer with tiled later views (forced at every image size) = the full warps (the
    default below TILED_MIN_PIXELS), bit for bit."""
    import presim.synthesis.cracks as cracks
    import presim.synthesis.pipeline as pipeline
    from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

    scene = S.make_scene(S.room_rects(), S.orbit_poses(6, span_m=1.2), K_SMALL)
    assert K_SMALL.width * K_SMALL.height < cracks.TILED_MIN_PIXELS
    poses = [make_pose(scene.T_world_cam[i][:3, :3], (scene.T_world_cam[i][:3, 3] + scene.T_world_cam[i + 1][:3, 3]) / 2)
             for i in range(4)]
    perf = PerfConfig(warp_ahead=False)  # the loop warps every view itself
    full = Renderer(scene, RenderConfig(), perf)
    want = [full.render(T, K_SMALL) for T in poses]
    tiled = Renderer(scene, RenderConfig(), perf)
    calls = []
    warp_tiles = pipeline.warp_tiles

    def counted(replace, *args):
        calls.append(1)
        return warp_tiles(replace, *args)

    monkeypatch.setattr(pipeline, "TILED_MIN_PIXELS", 0)
    monkeypatch.setattr(cracks, "TILED_MIN_PIXELS", 0)
    monkeypatch.setattr(pipeline, "warp_tiles", counted)
    n_later = 0
    for T, b in zip(poses, want):
        a = tiled.render(T, K_SMALL)
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        np.testing.assert_array_equal(a.valid, b.valid)
        n_later += len(tiled.last.views) - 1
    assert n_later > 0 and len(calls) == n_later  # later views were warped with tiles


@pytest.mark.parametrize("L", [1, 4])
def test_banded_pass_ignores_the_colour_of_empty_layer_pixels(L):
    """warp_layers(clear_color=False) leaves the colour planes as they were where a layer got no
    point (here: filled with garbage first); the banded crack pass reads colour only where the
    depth is > 0, so its output is the same as from cleared layers, with and without a replace
    mask, in bands and in tiles."""
    from presim.synthesis.cracks import filtered_composite_banded

    vp, T_cam_world = _room_view(L=L)
    clean = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
    rng = np.random.default_rng(L)
    dirty = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
    dirty.color[:] = rng.integers(1, 256, dirty.color.shape, dtype=np.uint8)
    dirty = warp_layers(vp, T_cam_world, K_SMALL, 1e-3, out=dirty, clear_color=False)
    empty = clean.depth_m == 0
    np.testing.assert_array_equal(dirty.depth_m, clean.depth_m)
    np.testing.assert_array_equal(dirty.color[~empty], clean.color[~empty])
    assert empty.any() and (dirty.color[empty] != 0).any()  # garbage left where no point landed
    mask = rng.random(empty.shape[1:]) < 0.3
    for replace, tile_cols in ((None, None), (mask, None), (mask, 8)):
        a = filtered_composite_banded(clean.depth_m, clean.color, replace, tile_cols=tile_cols)
        b = filtered_composite_banded(dirty.depth_m, dirty.color, replace, tile_cols=tile_cols)
        want = slice(None) if replace is None else replace
        np.testing.assert_array_equal(b[0][want], a[0][want])
        np.testing.assert_array_equal(b[1][want], a[1][want])


@pytest.mark.parametrize("L", [1, 4])
def test_banded_composite_matches_reference_on_warp(L):
    from presim.synthesis.cracks import filtered_composite_banded

    vp, T_cam_world = _room_view(L=L)
    lay = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
    d, c = _reference_view_chain(lay.depth_m, lay.color)
    bd, bc = filtered_composite_banded(lay.depth_m, lay.color)
    np.testing.assert_array_equal(bd, d)
    np.testing.assert_array_equal(bc, c)


def test_layer_slots_balance_known_answer():
    """Layers of 50, 40, 10 and 3 points over 2 threads: {50, 3} and {40, 10} (53 vs 50 points;
    equal chunks of the layer range would give 90 vs 13); every layer exactly once."""
    from presim.synthesis.warp import _layer_slots_kernel as layer_slots

    order, start = layer_slots(np.array([0, 50, 90, 100, 103]), 2)
    groups = [sorted(order[start[s]:start[s + 1]].tolist()) for s in range(2)]
    assert groups == [[0, 3], [1, 2]]
    order, start = layer_slots(np.array([0, 5, 5]), min(4, 2))  # 4 threads, 2 layers: the warp's clamp
    assert sorted(order.tolist()) == [0, 1] and start.tolist() == [0, 1, 2]


def test_warp_same_with_any_thread_count():
    """Each layer is warped by one thread, in point order: 1 and 2 threads give the same buffers."""
    import numba

    vp, T_cam_world = _room_view(L=4)
    old = numba.get_num_threads()
    outs = []
    try:
        for n in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(n)
            lay = warp_layers(vp, T_cam_world, K_SMALL, 1e-3)
            outs.append((lay.depth_m.copy(), lay.color.copy()))
    finally:
        numba.set_num_threads(old)
    assert (outs[0][0] > 0).mean() > 0.1
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


def test_chunk_bounds_match_numpy():
    """Bounds of each run of CHUNK_PTS points (the last run shorter) in a source camera's frame: ranges of
    x / z, y / z and z against numpy (float32, rounded outwards: they contain the float64 ranges, within 3
    float32 steps)."""
    from presim.synthesis.warp import CHUNK_PTS, chunk_bounds

    xyz = np.random.default_rng(3).normal(size=(5 * CHUNK_PTS + 17, 3)).astype(np.float32)
    T_src = look_at((0.3, -4.0, 0.5), (0.0, 0.0, 0.0))
    p = transform_points(invert(T_src), xyz.astype(np.float64))
    lo, hi = chunk_bounds(xyz, T_src)
    assert lo.dtype == hi.dtype == np.float32 and lo.shape == hi.shape == (3, 6)
    abz = np.column_stack([p[:, 0] / p[:, 2], p[:, 1] / p[:, 2], p[:, 2]])
    for c in range(6):
        part = abz[c * CHUNK_PTS:(c + 1) * CHUNK_PTS]
        assert (lo[:, c] <= part.min(0)).all() and (hi[:, c] >= part.max(0)).all()
        np.testing.assert_allclose(lo[:, c], part.min(0), rtol=5e-7)
        np.testing.assert_allclose(hi[:, c], part.max(0), rtol=5e-7)
    # A chunk with a point behind the source camera is unbounded (never culled).
    behind = xyz.copy()
    behind[CHUNK_PTS + 3] = transform_points(T_src, np.array([[0.0, 0.0, -1.0]]))[0]
    lo, hi = chunk_bounds(behind, T_src)
    assert np.isinf(lo[:, 1]).all() and np.isinf(hi[:, 1]).all() and np.isfinite(lo[:, [0, 2]]).all()
    # prepare_view keeps the source pose: its bounds are in the source frame.
    vp, _ = _room_view(L=4)
    np.testing.assert_array_equal(vp.chunk_lo, chunk_bounds(vp.xyz_world, vp.T_world_src)[0])
    with pytest.raises(ValueError, match="chunk must be >= 1"):
        chunk_bounds(xyz, T_src, 0)
    with pytest.raises(ValueError, match="finite 4x4"):
        chunk_bounds(xyz, np.full((4, 4), np.nan))


def test_chunk_visibility_known_answers():
    """Points 2 m in front of the camera: no chunk culled; the camera turned away (or the points
    behind its near plane, or all left of the image): every chunk culled; near <= 0: none."""
    from presim.synthesis.warp import CHUNK_PTS, ViewPoints, chunk_visibility

    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-0.3, 0.3, 640), rng.uniform(-0.3, 0.3, 640),
                           np.full(640, 2.0)]).astype(np.float32)
    vp = ViewPoints(xyz, np.zeros((640, 3), np.uint8), np.array([0, 640], np.int64), (2.0, 2.0), np.eye(4))
    n = -(-640 // CHUNK_PTS)
    eye = np.eye(4)
    assert chunk_visibility(vp, eye, K_SMALL).tolist() == [1] * n
    away = invert(look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0)))
    assert chunk_visibility(vp, away, K_SMALL).tolist() == [0] * n
    shift = np.eye(4)
    shift[2, 3] = -2.5  # the points 0.5 m behind the camera
    assert chunk_visibility(vp, shift, K_SMALL).tolist() == [0] * n
    left = np.eye(4)
    left[0, 3] = -3.0  # x in [-3.3, -2.7] at z = 2: far left of a 60 degree image
    assert chunk_visibility(vp, left, K_SMALL).tolist() == [0] * n
    assert chunk_visibility(vp, away, K_SMALL, near_m=0.0).tolist() == [1] * n


def test_culled_warp_is_exactly_the_full_warp():
    """Skipping the chunks chunk_visibility rules out changes no pixel, over random target cameras
    (many only partly facing the scene, some close to it) and sizes; some chunks are culled."""
    from presim.synthesis.warp import chunk_visibility

    rng = np.random.default_rng(7)
    culled = []
    for L in (1, 4):
        vp, _ = _room_view(L=L)
        for t in range(30):
            K = Intrinsics.from_fov(int(rng.integers(8, 120)), int(rng.integers(8, 90)), float(rng.uniform(30, 110)))
            eye = rng.uniform((-1.0, -1.5, 0.2), (1.0, 0.8, 1.8))
            T_cam_world = invert(look_at(eye, eye + rng.normal(size=3)))
            a = warp_layers(vp, T_cam_world, K, 1e-3)
            da, ca = a.depth_m.copy(), a.color.copy()
            b = warp_layers(vp, T_cam_world, K, 1e-3, cull=False)
            np.testing.assert_array_equal(da, b.depth_m)
            np.testing.assert_array_equal(ca, b.color)
            culled.append(1.0 - chunk_visibility(vp, T_cam_world, K).mean())
    culled = np.array(culled)
    assert (culled > 0).sum() >= 10 and (culled < 1).sum() >= 10 and ((culled > 0) & (culled < 1)).any()


def test_warp_in_blocks_gives_the_same_layers_for_any_block_size(monkeypatch):
    """The warp projects the kept chunks' points a block at a time (WARP_BLOCK_PTS): any block size
    gives the same layers (block boundaries anywhere in the layers, culled chunks between them)."""
    from dataclasses import replace

    from presim.synthesis import warp as W

    rng = np.random.default_rng(11)
    block0 = W.WARP_BLOCK_PTS
    for L in (1, 4):
        vp, T0 = _room_view(L=L)
        assert vp.xyz_world.shape[0] > 4 * block0
        cams = [(T0, K_SMALL)]
        for _ in range(6):
            K = Intrinsics.from_fov(int(rng.integers(8, 120)), int(rng.integers(8, 90)), float(rng.uniform(30, 110)))
            eye = rng.uniform((-1.0, -1.5, 0.2), (1.0, 0.8, 1.8))
            cams.append((invert(look_at(eye, eye + rng.normal(size=3))), K))
        for T_cam_world, K in cams:
            outs = []
            for block in (W.CHUNK_PTS, 3 * W.CHUNK_PTS, block0, 1 << 20):
                monkeypatch.setattr(W, "WARP_BLOCK_PTS", block)
                a = warp_layers(vp, T_cam_world, K, 1e-3)
                outs.append((a.depth_m.copy(), a.color.copy()))
            for d, c in outs[1:]:
                np.testing.assert_array_equal(d, outs[0][0])
                np.testing.assert_array_equal(c, outs[0][1])
    one = replace(vp, layer_start=np.array([0, vp.layer_start[-1]], np.int64))
    assert (warp_layers(one, T0, K_SMALL, 1e-3).depth_m > 0).mean() > 0.3


def test_culled_tiled_warp_is_exactly_the_full_warp_on_the_marked_tiles():
    """A tiled warp (later views) with culled chunks: the marked tiles (the only defined part of
    a tiled warp) equal the full warp's, for random marks and tile sizes."""
    from presim.synthesis.warp import chunk_visibility

    rng = np.random.default_rng(11)
    vp0, _ = _room_view(L=4)
    T_cam_world = invert(look_at((0.15, -0.9, 1.25), (1.6, 0.3, 0.4)))  # turned: part of the view is culled
    K = K_SMALL
    vis = chunk_visibility(vp0, T_cam_world, K)
    assert 0.1 < vis.mean() < 0.9
    full = warp_layers(vp0, T_cam_world, K, 1e-3, cull=False)
    assert (full.depth_m > 0).mean() > 0.02
    fd, fc = full.depth_m.copy(), full.color.copy()
    tile_culled = []
    for t in range(24):
        tile_px = int(rng.choice([4, 7, 16]))
        shape = (-(-K.height // tile_px), -(-K.width // tile_px))
        tiles = (rng.random(shape) < rng.uniform(0.02, 0.5)).astype(np.uint8)
        tiles[rng.integers(shape[0]), rng.integers(shape[1])] = 1
        on = np.repeat(np.repeat(tiles, tile_px, 0), tile_px, 1)[:K.height, :K.width].astype(bool)
        lay = warp_layers(vp0, T_cam_world, K, 1e-3, tiles=tiles, tile_px=tile_px)
        np.testing.assert_array_equal(lay.depth_m[:, on], fd[:, on])
        np.testing.assert_array_equal(lay.color[:, on], fc[:, on])
        tv = chunk_visibility(vp0, T_cam_world, K, 1e-3, tiles=tiles, tile_px=tile_px)
        assert (tv <= vis).all()  # the tiles only add culls
        tile_culled.append(vis.mean() - tv.mean())
    assert max(tile_culled) > 0.1  # the tiles cull chunks the frustum keeps


def test_tile_culled_warp_is_exact_for_random_cameras():
    """Tile culling over random target cameras, sizes, tile sizes and marks: the marked tiles equal the
    full warp's."""
    from presim.synthesis.warp import chunk_visibility

    rng = np.random.default_rng(5)
    vp, _ = _room_view(L=4)
    culled = 0
    for t in range(40):
        K = Intrinsics.from_fov(int(rng.integers(8, 120)), int(rng.integers(8, 90)), float(rng.uniform(30, 110)))
        eye = rng.uniform((-1.0, -1.5, 0.2), (1.0, 0.8, 1.8))
        T_cam_world = invert(look_at(eye, eye + rng.normal(size=3)))
        full = warp_layers(vp, T_cam_world, K, 1e-3, cull=False)
        fd, fc = full.depth_m.copy(), full.color.copy()
        tile_px = int(rng.choice([1, 3, 8, 16]))
        shape = (-(-K.height // tile_px), -(-K.width // tile_px))
        tiles = (rng.random(shape) < rng.uniform(0.01, 0.6)).astype(np.uint8)
        on = np.repeat(np.repeat(tiles, tile_px, 0), tile_px, 1)[:K.height, :K.width].astype(bool)
        lay = warp_layers(vp, T_cam_world, K, 1e-3, tiles=tiles, tile_px=tile_px)
        np.testing.assert_array_equal(lay.depth_m[:, on], fd[:, on])
        np.testing.assert_array_equal(lay.color[:, on], fc[:, on])
        frustum = chunk_visibility(vp, T_cam_world, K, 1e-3)
        culled += int((chunk_visibility(vp, T_cam_world, K, 1e-3, tiles=tiles, tile_px=tile_px) < frustum).any())
    assert culled >= 4


def test_tile_marks_are_checked_and_a_turned_scene_warps_exactly():
    """Tiles of the wrong shape or type are an error naming the caller; a scene turned off the axes (thin
    world boxes would not help) still warps the marked tiles exactly."""
    from presim.synthesis.warp import ViewPoints, chunk_visibility

    vp0, _ = _room_view(L=4)
    turn = make_pose(np.array([[0.8, -0.6, 0.0], [0.48, 0.64, -0.6], [0.36, 0.48, 0.8]]), np.zeros(3))
    xyz = transform_points(turn, vp0.xyz_world.astype(np.float64)).astype(np.float32)
    vp = ViewPoints(xyz, vp0.rgb, vp0.layer_start, vp0.depth_range_m, turn @ vp0.T_world_src)
    tiles = np.zeros((-(-K_SMALL.height // 8), -(-K_SMALL.width // 8)), np.uint8)
    tiles[2:4, 3:6] = 1
    T_near = invert(turn @ look_at((0.15, -0.9, 1.25), (0.0, 0.5, 0.4)))
    assert 0 < chunk_visibility(vp, T_near, K_SMALL, tiles=tiles, tile_px=8).sum() < len(vp.chunk_lo[0])
    with pytest.raises(ValueError, match="chunk_visibility: tiles must be uint8"):
        chunk_visibility(vp, T_near, K_SMALL, tiles=tiles[:-1], tile_px=8)
    with pytest.raises(ValueError, match="tiles must be uint8"):
        chunk_visibility(vp, T_near, K_SMALL, tiles=tiles.astype(bool), tile_px=8)
    full = warp_layers(vp, T_near, K_SMALL, 1e-3, cull=False)
    fd = full.depth_m.copy()
    lay = warp_layers(vp, T_near, K_SMALL, 1e-3, tiles=tiles, tile_px=8)
    on = np.repeat(np.repeat(tiles, 8, 0), 8, 1)[:K_SMALL.height, :K_SMALL.width].astype(bool)
    assert (fd[:, on] > 0).any()
    np.testing.assert_array_equal(lay.depth_m[:, on], fd[:, on])
