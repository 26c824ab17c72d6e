"""Small-frame fast paths (issue 13): the fused merge + hole mask, the hole analysis from that mask,
the numba LOD median and grid counts — each equal, bit for bit, to the path or numpy expression it
replaces."""

from __future__ import annotations

import cv2
import numba
import numpy as np
import pytest

from presim.synthesis.holes import analyse_hole_mask, merge_view_holes


def test_merge_view_holes_equals_merge_then_mask():
    """Fused merge + hole mask + count = the numpy merge, then ``acc > 0``; the first view (no
    replace mask) only writes its source ids."""
    rng = np.random.default_rng(5)
    H, W = 21, 26
    d1 = np.where(rng.random((H, W)) < 0.6, rng.random((H, W)) + 0.1, 0).astype(np.float32)
    d1[0, 0] = np.nan  # not > 0: a hole
    c1 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    src = np.full((H, W), 99, np.int32)
    holes = np.empty((H, W), np.uint8)
    n = merge_view_holes(d1, c1, src, None, d1, c1, 4, holes)
    np.testing.assert_array_equal(src, np.where(d1 > 0, 4, -1))
    np.testing.assert_array_equal(holes, (~(d1 > 0)).view(np.uint8))
    assert n == np.count_nonzero(~(d1 > 0))
    replace = analyse_hole_mask(holes, n, 4, 1).replace
    d2 = np.where(rng.random((H, W)) < 0.7, rng.random((H, W)) + 0.1, 0).astype(np.float32)
    c2 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    ref = [a.copy() for a in (d1, c1, src)]  # numpy reference of the merge
    take = replace & (d2 > 0)
    ref[0][take], ref[1][take], ref[2][take] = d2[take], c2[take], 9
    assert 0 < take.sum() < take.size
    acc = [a.copy() for a in (d1, c1, src)]
    n = merge_view_holes(*acc, replace, d2, c2, 9, holes)
    for a, b in zip(acc, ref):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(holes, (~(ref[0] > 0)).view(np.uint8))
    assert n == np.count_nonzero(~(ref[0] > 0))


@pytest.mark.parametrize("words", ["words", "pixels"])
def test_merge_into_holes_equals_merge_view_holes(words, monkeypatch):
    """A later view's merge that updates the previous hole mask in place (visiting only the
    replaceable pixels, 8 at a time) = the full merge + mask + count, over a chain of views; widths
    that are and are not multiples of 8 (zero-padded words), and the kernel's pixel-by-pixel path
    (no words); NaN depths, empty replace masks."""
    from presim.synthesis import holes as HO
    from presim.synthesis.holes import merge_into_holes

    if words == "pixels":
        monkeypatch.setattr(HO, "row_words", lambda m: np.zeros((m.shape[0], 0), np.uint64))
    rng = np.random.default_rng(9)
    for H, W in ((21, 26), (17, 24), (9, 64), (1, 8), (6, 3), (4, 9)):
        d0 = np.where(rng.random((H, W)) < 0.5, rng.random((H, W)) + 0.1, 0).astype(np.float32)
        d0.flat[::13] = np.nan
        c0 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        ref = [d0.copy(), c0.copy(), np.empty((H, W), np.int32)]
        new = [d0.copy(), c0.copy(), np.empty((H, W), np.int32)]
        h_ref = np.empty((H, W), np.uint8)
        h_new = np.empty((H, W), np.uint8)
        n_ref = merge_view_holes(ref[0], ref[1], ref[2], None, ref[0], ref[1], 1, h_ref)
        n_new = merge_view_holes(new[0], new[1], new[2], None, new[0], new[1], 1, h_new)
        for k in range(2, 7):
            replace = analyse_hole_mask(h_ref.copy(), n_ref, 4, 1).replace
            if k == 4:
                replace = np.zeros((H, W), bool)
            d = np.where(rng.random((H, W)) < 0.4, rng.random((H, W)) + 0.1, 0).astype(np.float32)
            d.flat[::7] = np.nan
            c = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            n_ref = merge_view_holes(*ref, replace, d, c, k, h_ref)
            n_new -= merge_into_holes(*new, replace, d, c, k, h_new)
            for a, b in zip(ref, new):
                np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(h_ref, h_new)
            np.testing.assert_array_equal(h_new, (~(new[0] > 0)).view(np.uint8))
            assert n_new == n_ref
        assert n_ref < np.count_nonzero(~(d0 > 0))  # the chain filled some holes


def test_hole_runs_components_equal_scipy_labelling():
    """The run + union-find labelling of the hole analysis = scipy's 8-connected labelling on
    random masks (sparse to full, clustered, widths with and without 8-pixel groups, one row, one
    column), a checkerboard and diagonal chains (8-connected across corners only): largest area,
    any big, and the big-hole mask; an n_hole below the mask's count is refused."""
    from scipy import ndimage

    from presim.imaging.masks import row_words
    from presim.synthesis.holes import _NO_HALF, _NO_U8, _ellipse_rows, _hole_runs_kernel

    rng = np.random.default_rng(21)
    masks = []
    for t in range(300):
        H = int(rng.integers(1, 50))
        W = 8 * int(rng.integers(1, 9)) if t % 2 else int(rng.integers(1, 60))
        m = rng.random((H, W)) < rng.uniform(0.0, 1.0)
        if t % 3 == 0:
            m = ndimage.binary_opening(m) | (rng.random((H, W)) < 0.03)
        masks.append(m)
    masks += [np.indices((20, 24)).sum(0) % 2 == 0, np.eye(17, 40, dtype=bool) | np.eye(17, 40, 3, dtype=bool),
              np.ones((1, 33), bool), np.ones((29, 1), bool), np.zeros((5, 16), bool)]
    for m in masks:
        holes = np.ascontiguousarray(m.astype(np.uint8))
        lab, n = ndimage.label(m, structure=np.ones((3, 3)))
        areas = np.bincount(lab.ravel(), minlength=n + 1)[1:]
        # zero groups skipped as words (zero-padded past W when W % 8 != 0), and pixel by pixel
        for words in (row_words(holes), np.zeros((holes.shape[0], 0), np.uint64)):
            for big_px in (1, 16):
                big = np.empty(holes.shape, np.uint8)
                replace = np.empty(holes.shape, np.uint8)
                k = 2 * (big_px % 4) + 3  # 5 and 3: the replace mask's dilation, against OpenCV's
                largest, any_big = _hole_runs_kernel(holes, words, int(holes.sum()), big_px, big,
                                                     _ellipse_rows(k), replace)
                assert largest == (areas.max() if n else 0)
                ref = np.isin(lab, 1 + np.flatnonzero(areas >= big_px))
                np.testing.assert_array_equal(big.view(bool), ref)
                assert any_big == bool(ref.any())
                want = holes | cv2.dilate(ref.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
                np.testing.assert_array_equal(replace, want)
    holes = np.ones((4, 8), np.uint8)
    with pytest.raises(ValueError, match="n_hole"):
        _hole_runs_kernel(holes, row_words(holes), 3, 16, np.empty((0, 0), np.uint8), _NO_HALF, _NO_U8)


def test_row_words_are_the_rows_zero_padded_to_8_pixels():
    """row_words: a C-contiguous mask whose width is a multiple of 8 is viewed as uint64 rows (no
    copy); any other width, or a strided mask, is copied into rows zero-padded to a multiple of 8;
    the bytes of the words are the mask's pixels in order."""
    from presim.imaging.masks import row_words

    rng = np.random.default_rng(3)
    for H, W in ((3, 16), (5, 13), (1, 1), (4, 7), (2, 638)):
        m = (rng.random((H, W)) < 0.5).astype(np.uint8)
        for mask in (m, np.repeat(m, 2, axis=1)[:, ::2]):  # contiguous, strided
            w = row_words(mask)
            assert w.dtype == np.uint64 and w.shape == (H, -(-W // 8))
            b = w.view(np.uint8).reshape(H, -1)
            np.testing.assert_array_equal(b[:, :W], m)
            assert not b[:, W:].any()
            assert np.shares_memory(w, mask) == (W % 8 == 0 and mask.flags.c_contiguous)
    assert row_words(np.zeros((4, 0), np.uint8)).shape == (4, 0)


def test_footprint_median_equals_numpy_median():
    """LOD footprint median: numpy's ``np.median(z_s[ok] / z_t[ok])`` with ``ok`` from float32
    comparisons and the in-image test, exactly (odd / even counts, ties, inputs in increasing and
    decreasing order, a few points and a few hundred, none ok -> nan)."""
    from presim.geometry import Intrinsics
    from presim.synthesis.grids import FrameGrids

    K = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    rng = np.random.default_rng(0)
    for t in range(400):
        n = int(rng.integers(0, 40 if t % 2 else 400))
        zs = rng.uniform(-0.5, 3, n).astype(np.float32)
        zt = rng.uniform(-0.5, 3, n).astype(np.float32)
        if t % 3 == 0 and n:
            zs[: n // 2] = zs[0]
        if t % 5 == 0:  # sorted by ratio, increasing or decreasing (quickselect's worst orders)
            o = np.argsort(zs / zt, kind="stable")[:: 1 if t % 10 else -1]
            zs, zt = zs[o].copy(), zt[o].copy()
        near = 0.1  # float32(0.1) > 0.1: numpy compares in float32
        zs[: n // 4] = np.float32(near)
        pix = np.where(rng.random(n) < 0.2, -1, rng.integers(0, 1000, n)).astype(np.int64)  # -1: outside
        ok = (zs > near) & (zt > near) & (pix >= 0)
        g = FrameGrids(np.eye(4), K, lambda v: np.zeros((n, 3), np.float32))
        g._proj[0] = (pix, zt)
        got = g.footprint_ratio(0, zs, 100.0, near)
        if not ok.any():
            assert np.isnan(got)
            continue
        assert got == float(np.median(zs[ok] / zt[ok]) * np.sqrt(K.fx * K.fy) / 100.0)


def test_frame_grids_lod_level_is_choose_level_of_the_footprint_median():
    """FrameGrids.lod_level = choose_level of the footprint median (identity target camera: the
    grid's points on the optical axis at z_t, their source depths z_src = ratio x z_t; odd and even
    counts, ratios on every level); no levels: level 0."""
    from presim.geometry import Intrinsics
    from presim.synthesis.grids import FrameGrids
    from presim.synthesis.lod import LodConfig, choose_level

    cfg = LodConfig()
    f_t, f_s = 150.0, 525.0
    K = Intrinsics(f_t, f_t, 31.5, 23.5, 64, 48)
    levels = []
    for ratios in ([2.0, 1.8], [1.0, 0.9], [0.5, 0.45, 0.4], [0.2], [0.3, 0.1, 5.0, 7.0], [0.4, 0.35, 3.0]):
        ratios = np.float32(ratios)
        z_t = np.linspace(1.0, 2.0, len(ratios)).astype(np.float32)
        pts = np.stack([np.zeros_like(z_t), np.zeros_like(z_t), z_t], 1)
        g = FrameGrids(np.eye(4), K, lambda v: pts)
        z_src = (ratios * z_t).astype(np.float32)
        r0 = g.footprint_ratio(0, z_src, f_s, 0.01)
        assert r0 == pytest.approx(float(np.median(ratios)) * f_t / f_s, rel=1e-6)
        want = choose_level(r0, cfg)
        assert g.lod_level(0, z_src, f_s, 0.01, cfg) == want
        assert g.lod_level(0, z_src, f_s, 0.01, LodConfig(levels=0)) == 0
        levels.append(want)
    assert levels == [0, 1, 2, 3, 0, 3]


def test_lod_level_by_counts_is_choose_level_of_the_median(monkeypatch):
    """FrameGrids.lod_level (counts of the ratios under each level's float32 threshold) = choose_level of the
    exact median, on random grids whose ratios sit at, just below and just above the thresholds, odd and even
    counts (a threshold between the two middle ratios), points behind the cameras, other focal lengths and
    footprints."""
    from presim.geometry import Intrinsics
    from presim.synthesis.grids import FrameGrids, _level_taus
    from presim.synthesis.lod import LodConfig, choose_level

    rng = np.random.default_rng(4)
    seen, medians = set(), []
    exact = FrameGrids.footprint_ratio
    monkeypatch.setattr(FrameGrids, "footprint_ratio", lambda self, *a: medians.append(1) or exact(self, *a))
    for trial in range(300):
        cfg = LodConfig(levels=int(rng.integers(1, 5)), max_footprint=float(rng.choice([1.0, 0.7, 2.5])))
        f_t, f_s = float(rng.uniform(40, 600)), float(rng.uniform(200, 900))
        K = Intrinsics(f_t, f_t * float(rng.uniform(0.9, 1.1)), 31.5, 23.5, 64, 48)
        taus = _level_taus(np.sqrt(K.fx * K.fy), f_s, cfg)
        n = int(rng.integers(1, 12))
        pick = rng.choice(taus[1:], n)
        near = np.array([np.nextafter(pick, np.float32(0)), pick, np.nextafter(pick, np.float32(9))])
        ratios = np.where(rng.random(n) < 0.7, near[rng.integers(0, 3, n), np.arange(n)],
                          rng.uniform(0.01, 2.0 * float(taus[1]) + 0.01, n)).astype(np.float32)
        z_t = np.ones(n, np.float32)  # ratio = z_src exactly
        pts = np.stack([np.zeros(n), np.zeros(n), np.linspace(1.0, 2.0, n)], 1).astype(np.float32)
        g = FrameGrids(np.eye(4), K, lambda v: pts)
        g.project([0])
        g._proj[0] = (g._proj[0][0], z_t)
        z_src = ratios.copy()
        z_src[rng.random(n) < 0.1] = -1.0  # behind the source camera: not counted
        want = choose_level(exact(g, 0, z_src, f_s, 0.01), cfg)
        assert g.lod_level(0, z_src, f_s, 0.01, cfg) == want, (trial, ratios, z_src, taus)
        seen.add(want)
    assert seen == {0, 1, 2, 3, 4}
    assert 0 < len(medians) < 100  # a threshold between the two middle ratios: the median decides


def test_grid_count_kernels_equal_numpy():
    from presim.synthesis.grids import _count_front_kernel, count_in_mask

    rng = np.random.default_rng(1)
    pix = rng.integers(-1, 500, 300).astype(np.int64)
    z = rng.uniform(-1, 2, 300).astype(np.float32)
    z[:20] = np.float32(0.01)
    ok = (pix >= 0) & (z > 0.01)
    assert _count_front_kernel(pix, z, np.float32(0.01)) == np.count_nonzero(ok)
    mask = rng.random(500) < 0.3
    px = pix[ok]
    assert count_in_mask(mask, px) == np.count_nonzero(mask[px])
    assert count_in_mask(mask, px[:0]) == 0



def test_frame_threads_rule():
    """Auto: one numba thread up to SERIAL_MAX_PIXELS, the caller's count above; explicit counts are
    capped at numba's pool; a negative count is an error (here and in PerfConfig)."""
    from presim.synthesis.renderer import PerfConfig
    from presim.numba_threads import SERIAL_MAX_PIXELS, frame_threads, numba_threads

    assert frame_threads(128, 128) == 1
    assert frame_threads(SERIAL_MAX_PIXELS, 1) == 1
    assert frame_threads(SERIAL_MAX_PIXELS + 1, 1) == numba.get_num_threads()
    assert frame_threads(640, 480, 1) == 1
    assert frame_threads(64, 48, 10_000) == numba.config.NUMBA_NUM_THREADS
    with numba_threads(1):
        assert numba.get_num_threads() == 1
        assert frame_threads(640, 480) == 1  # a caller that lowered the count keeps it
    with pytest.raises(ValueError, match="threads"):
        frame_threads(64, 48, -1)
    with pytest.raises(ValueError, match="threads must be >= 0"):
        PerfConfig(threads=-1)


def test_small_frames_render_on_one_thread_with_the_same_image(monkeypatch):
    """A small frame's core runs with one numba thread (auto), a large one with the caller's count,
    the caller's count is restored afterwards, and forcing two threads gives the same image."""
    from presim.geometry import Intrinsics, look_at
    from presim.synthesis import renderer as R
    from presim.numba_threads import serial_now
    from presim.testing import rect_scene as S

    K = Intrinsics.from_fov(64, 48, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(4), K)
    T = look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4))
    seen = []
    core = R.synthesize_frame

    def spy(*a, **kw):
        seen.append((numba.get_num_threads(), serial_now()))
        return core(*a, **kw)

    monkeypatch.setattr(R, "synthesize_frame", spy)
    before = numba.get_num_threads()
    auto = R.Renderer(scene, R.RenderConfig()).render(T, K)
    forced = R.Renderer(scene, R.RenderConfig(), R.PerfConfig(threads=numba.config.NUMBA_NUM_THREADS)).render(T, K)
    wide = Intrinsics(fx=K.fx, fy=K.fy, cx=199.5, cy=149.5, width=400, height=300)  # no zoom: 120 000 px
    R.Renderer(scene, R.RenderConfig()).render(T, wide)
    n = numba.config.NUMBA_NUM_THREADS
    # one thread = the serial twins of the parallel kernels (serial_now); more = the parallel ones
    assert seen == [(1, True), (n, n == 1), (before, before == 1)]
    assert numba.get_num_threads() == before and not serial_now()
    np.testing.assert_array_equal(auto.color, forced.color)
    np.testing.assert_array_equal(auto.depth_m, forced.depth_m)


def test_numba_kernels_use_numpy_error_model():
    """Every numba kernel of the synthesis and of imaging (both twins of a TwinKernel) is compiled with numpy's
    error model: no ZeroDivisionError branch in the loops, which keeps LLVM from vectorizing any
    loop with a division or a modulo (docs/synthesis.md, "numpy's error model")."""
    import importlib

    from numba.core.registry import CPUDispatcher

    from presim.numba_threads import TwinKernel

    seen = 0
    for name in ("synthesis.blend", "synthesis.cracks", "synthesis.holes", "synthesis.grids", "synthesis.resample",
                 "synthesis.warp", "synthesis.warp_ahead", "imaging.inpaint", "imaging.pool", "imaging.pushpull"):
        mod = importlib.import_module(f"presim.{name}")
        for attr, obj in vars(mod).items():
            if isinstance(obj, TwinKernel):
                dispatchers = [obj.parallel, obj.serial]
            elif isinstance(obj, CPUDispatcher):
                dispatchers = [obj]
            else:
                continue
            if getattr(obj, "__module__", mod.__name__) != mod.__name__:
                continue  # imported from another module: checked there
            for d in dispatchers:
                assert d.targetoptions.get("error_model") == "numpy", f"{name}.{attr}"
                seen += 1
    assert seen >= 60


def test_light_kernels_run_their_serial_twin_below_their_size():
    """A TwinKernel with serial_below runs the serial twin when its size argument is smaller (and in
    serial mode), the parallel one otherwise; the per-view light kernels declare their sizes, and
    their output does not depend on which twin ran."""
    from presim.imaging import pushpull as F
    from presim.synthesis import holes as C
    from presim.numba_threads import LIGHT_SERIAL_BELOW, TwinKernel, parallel_kernel, serial_kernels

    def _double(a, out):  # pragma: no cover
        for i in numba.prange(a.shape[0]):
            out[i] = 2 * a[i]

    k = parallel_kernel(serial_below=100, size_arg=1)(_double)
    assert isinstance(k, TwinKernel) and (k.serial_below, k.size_arg) == (100, 1)
    calls = []
    par, ser = k.parallel, k.serial
    k.parallel = lambda *a: (calls.append("parallel"), par(*a))[1]
    k.serial = lambda *a: (calls.append("serial"), ser(*a))[1]
    for n in (99, 100, 5000):
        out = np.zeros(n)
        k(np.arange(n, dtype=np.float64), out)
        np.testing.assert_array_equal(out, 2 * np.arange(n))
    with serial_kernels():
        k(np.arange(500.0), np.zeros(500))
    assert calls == ["serial", "parallel", "parallel", "serial"]
    # the declared sizes: per pixel of the image each one passes over
    assert (C._merge_holes_kernel.serial_below, C._merge_holes_kernel.size_arg) == (LIGHT_SERIAL_BELOW["pass"], 0)
    assert (C._merge_into_holes_kernel.serial_below, C._merge_into_holes_kernel.size_arg) == (LIGHT_SERIAL_BELOW["map"], 0)
    assert (F._pull0_kernel.serial_below, F._pull0_kernel.size_arg) == (LIGHT_SERIAL_BELOW["pass"], 1)
    assert (F._push0_kernel.serial_below, F._push0_kernel.size_arg) == (LIGHT_SERIAL_BELOW["pass"], 0)
    rng = np.random.default_rng(5)
    H, W = 90, 70
    acc = [rng.random((H, W)).astype(np.float32), rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
           np.zeros((H, W), np.int32)]
    d = np.where(rng.random((H, W)) < 0.5, 1.0, 0.0).astype(np.float32)
    replace = rng.random((H, W)) < 0.3
    outs = []
    for twin in (C._merge_holes_kernel.parallel, C._merge_holes_kernel):  # 6300 px: the serial twin
        a = [x.copy() for x in acc]
        holes = np.empty((H, W), np.uint8)
        n = twin(*a, replace, d, acc[1], np.int32(3), False, holes)
        outs.append((a, holes, n))
    for x, y in zip(outs[0][0] + [outs[0][1]], outs[1][0] + [outs[1][1]]):
        np.testing.assert_array_equal(x, y)
    assert outs[0][2] == outs[1][2]


def test_twin_kernels_dispatch_by_the_threads_mode_and_agree():
    """A parallel kernel declared with parallel_kernel runs its serial twin inside serial_kernels()
    / numba_threads(1) (and in threads started there only when they ask), the parallel one
    otherwise; both give the same output, and the serial twin runs without the GIL."""
    import threading

    from presim.imaging.pool import _pool_kernel, pool_depth_aware
    from presim.numba_threads import TwinKernel, numba_threads, serial_kernels, serial_now

    assert isinstance(_pool_kernel, TwinKernel)
    assert _pool_kernel.serial.targetoptions.get("nogil") and _pool_kernel.parallel.targetoptions.get("parallel")
    rng = np.random.default_rng(3)
    d = rng.uniform(0.5, 3.0, (40, 52)).astype(np.float32)
    d[rng.random(d.shape) < 0.2] = 0.0
    c = rng.integers(0, 256, (40, 52, 3), dtype=np.uint8)
    calls = []
    orig = {twin: getattr(_pool_kernel, twin) for twin in ("parallel", "serial")}
    for twin, k in orig.items():
        setattr(_pool_kernel, twin, lambda *a, _k=k, _t=twin: (calls.append(_t), _k(*a))[1])
    try:
        par = pool_depth_aware(d, c, 0.02)
        with serial_kernels():
            ser = pool_depth_aware(d, c, 0.02)
            assert serial_now()
            with numba_threads(2):  # asking for threads inside serial mode keeps the twins serial
                assert serial_now()
            seen = []
            t = threading.Thread(target=lambda: seen.append(serial_now()))  # per Python thread
            t.start()
            t.join()
            assert seen == [False]
        with numba_threads(1):
            one = pool_depth_aware(d, c, 0.02)
        assert not serial_now()
    finally:
        for twin, k in orig.items():
            setattr(_pool_kernel, twin, k)
    assert calls == ["parallel", "serial", "serial"]
    for a, b in ((par, ser), (par, one)):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
