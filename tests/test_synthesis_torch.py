"""Torch kernels of the stages after the view image (presim/synthesis/torch_stages.py, the pull-push of
presim/imaging/torch_ops.py) against their numba / numpy paths on CPU torch, and the torch backend end to end
against numba."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from scipy import ndimage  # noqa: E402

from presim.capture.calibration import PhotometricCalib  # noqa: E402
from presim.geometry import Intrinsics, look_at  # noqa: E402
from presim.imaging import torch_ops  # noqa: E402
from presim.imaging.pushpull import pushpull_rgbd  # noqa: E402
from presim.photometric.apply import apply_exposure, correct_colors  # noqa: E402
from presim.synthesis import torch_stages as ts  # noqa: E402
from presim.synthesis.blend import BlendConfig, BlendInput, blend_reference  # noqa: E402
from presim.synthesis.holes import analyse_hole_mask, merge_into_holes, merge_view_holes  # noqa: E402
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer  # noqa: E402
from presim.testing import rect_scene as S  # noqa: E402

K = Intrinsics.from_fov(64, 48, 60.0)


@pytest.fixture(scope="module")
def room():
    return S.make_scene(S.room_rects(), S.orbit_poses(4), K)


def test_merge_matches_numba():
    rng = np.random.default_rng(0)
    H, W = 23, 31

    def image():
        d = np.where(rng.random((H, W)) < 0.6, rng.uniform(1, 3, (H, W)), 0).astype(np.float32)
        return d, rng.integers(0, 256, (H, W, 3), dtype=np.uint8)

    d0, c0 = image()
    d1, c1 = image()
    replace = rng.random((H, W)) < 0.5
    out = []
    for first, later in ((merge_view_holes, merge_into_holes),
                         (lambda *a: ts.merge_holes_torch(*a, device="cpu"),) * 2):
        acc_d, acc_c, src, holes = d0.copy(), c0.copy(), np.empty((H, W), np.int32), np.empty((H, W), np.uint8)
        n0 = first(acc_d, acc_c, src, None, acc_d, acc_c, 4, holes)
        snap = (src.copy(), holes.copy())
        n1 = later(acc_d, acc_c, src, replace, d1, c1, 7, holes)
        out.append((n0, n1, snap, acc_d, acc_c, src, holes))
    (n0, n1, snap, *arrays), (t0, t1, tsnap, *tarrays) = out
    assert (n0, n1) == (t0, t1) and n0 == (d0 <= 0).sum() and n1 > 0
    for a, b in zip(list(snap) + arrays, list(tsnap) + tarrays):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def _spiral(n: int) -> np.ndarray:
    h = np.zeros((n, n), np.uint8)
    y0 = x0 = 0
    y1 = x1 = n - 1
    while y0 <= y1 and x0 <= x1:
        h[y0, x0:x1 + 1] = h[y0:y1 + 1, x1] = h[y1, x0:x1 + 1] = 1
        h[y0 + 2:y1 + 1, x0] = 1
        y0, x0, y1, x1 = y0 + 2, x0 + 2, y1 - 2, x1 - 2
    return h


def _masks(room):
    rng = np.random.default_rng(1)
    for p in (0.05, 0.3, 0.45, 0.6, 0.95):  # 8-connected percolation near 0.41: long, branching holes
        for shape in ((1, 1), (1, 17), (13, 1), (37, 53)):
            yield (rng.random(shape) < p).astype(np.uint8)
    yield _spiral(41)
    yield np.eye(20, dtype=np.uint8)[::-1].copy()  # one diagonal: a single 8-connected hole
    Kr = Intrinsics.from_fov(160, 120, 60.0)  # real holes: cracks, disocclusions, the border
    for v in (1, 3):
        out = Renderer(room, RenderConfig(fill_holes=False, fixed_views=v)).render(
            look_at((0.3, -1.0, 1.25), (0.0, 0.5, 0.4)), Kr)
        yield (~out.valid).view(np.uint8)


@pytest.mark.parametrize("kw", [{}, {"big_hole_px": 1, "hole_dilation_px": 3}, {"hole_dilation_px": 0},
                                {"want_replace": False}, {"stop_px": 40.0}])
def test_hole_analysis_matches_numba(room, kw):
    for holes in _masks(room):
        n = int(holes.sum())
        a = analyse_hole_mask(holes, n, **kw)
        b = ts.analyse_hole_mask_torch(holes, n, device="cpu", **kw)
        assert (a.hole_frac, a.largest_hole_px) == (b.hole_frac, b.largest_hole_px)
        for x, y in ((a.replace, b.replace), (a.big, b.big)):
            assert (x is None) == (y is None)
            assert x is None or (x.dtype == y.dtype and np.array_equal(x, y))


def test_component_labels_are_scipys_8_connected_components(room):
    for holes in _masks(room):
        lab = torch_ops.label_components_torch(torch.from_numpy(holes != 0)).numpy()
        ref, _ = ndimage.label(holes, np.ones((3, 3)))
        m = holes != 0
        assert np.array_equal(lab < 0, ~m)
        pairs = np.unique(np.stack([lab[m], ref[m]]), axis=1)  # one scipy label per torch label and back
        assert len(np.unique(pairs[0])) == len(np.unique(pairs[1])) == pairs.shape[1]
        assert np.all(np.take(np.arange(holes.size), lab[m]) <= np.flatnonzero(m))  # the smallest index in it
    lab = torch_ops.label_components_torch(torch.tensor([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 0, 0], [1, 1, 0, 1]]).bool())
    assert lab.tolist() == [[0, -1, -1, 3], [-1, 0, -1, 3], [-1, -1, -1, -1], [12, 12, -1, 15]]


@pytest.mark.parametrize("shape,known_frac", [((8, 10), 0.3), ((30, 42), 0.05), ((48, 64), 0.9), ((31, 41), 0.4),
                                              ((1, 9), 0.3), ((7, 1), 0.5), ((96, 128), 0.02)])
def test_pushpull_matches_numba(shape, known_frac):
    rng = np.random.default_rng(shape[0])
    color = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    depth = rng.uniform(1, 2, shape).astype(np.float32)
    valid = rng.random(shape) < known_frac
    valid.flat[0] = True
    c, d = pushpull_rgbd(color, depth, valid)
    tc, td = torch_ops.pushpull_rgbd_torch(color, depth, valid, device="cpu")
    assert tc.dtype == np.uint8 and td.dtype == np.float32
    np.testing.assert_array_equal(tc[valid], color[valid])
    np.testing.assert_array_equal(td[valid], depth[valid])
    # Same weights, float32 sums in another order (measured <= 5e-7 m here); the colour's +0.5 truncation may
    # flip one level where a value sits within float error of .5 (the numba-vs-OpenCV rule of test_synthesis_core).
    assert np.abs(td - d).max() < 1e-5
    assert np.abs(tc.astype(int) - c).max() <= 1 and np.mean(tc != c) < 0.01
    assert np.array_equal(torch_ops.pushpull_rgbd_torch(None, depth, valid, device="cpu")[1], td)


def _blend_inputs(seed: int):
    rng = np.random.default_rng(seed)
    H, W, n = 30, 40, 3
    depth = rng.uniform(1.0, 2.0, (H, W)).astype(np.float32)
    depth[:3] = 0
    vd = np.repeat(depth[None], n, 0) * rng.choice([1.0, 1.005, 1.3], (n, H, W)).astype(np.float32)
    vd[:, :, :2] = 0
    return BlendInput(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), depth,
                      rng.choice([-1, 4, 7, 9], (H, W)).astype(np.int32), np.array([4, 7, 9], np.int32), vd,
                      rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8),
                      rng.normal(0, 0.2, (n, 3)), np.array([1.0, 0.5, 2.0])), Intrinsics.from_fov(W, H, 60.0)


@pytest.mark.parametrize("cfg", [BlendConfig(depth_tol_rel=0.02, feather_px=4.0), BlendConfig(),
                                 BlendConfig(feather_px=1.0), BlendConfig(feather_px=20.0, resolution_weight=0.5)])
def test_blend_matches_reference(cfg):
    T = look_at((0.0, 0.0, 0.0), (0.1, 0.0, 2.0))
    for seed in (0, 1):
        inp, Kt = _blend_inputs(seed)
        a = ts.blend_torch(inp, Kt, T, cfg, device="cpu").astype(int)
        b = blend_reference(inp, Kt, T, cfg).astype(int)
        # float64 as the reference, other summation order: test_blend's numba rule (measured: equal)
        assert np.abs(a - b).max() <= 1 and (a != b).mean() < 0.01
        assert np.array_equal(a[:3], inp.color[:3]) and (a != inp.color).mean() > 0.3


def test_exposure_matches_numba():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    img[0, 0] = 0
    for A in (np.diag([1.1, 0.9, 1.3]), np.array([[1.05, 0.02, -0.01], [0.03, 0.95, 0.0], [0.0, -0.02, 1.2]])):
        for b in (np.zeros(3), np.array([3.0, -2.5, 0.5])):
            got = ts.apply_exposure_torch(img, A, b, device="cpu")
            assert np.array_equal(got, apply_exposure(img, A, b))
            assert np.array_equal(got, correct_colors(img, np.eye(3), np.zeros(3), A, b))
            assert (got[0, 0] == 0).all() and (got != img).any()


def test_torch_backend_renders_as_numba_and_runs_the_torch_stages(room, monkeypatch):
    calls = []
    names = ("merge_holes_torch", "analyse_hole_mask_torch", "pushpull_rgbd_torch", "blend_torch",
             "apply_exposure_torch")
    for name in names:
        mod = torch_ops if name == "pushpull_rgbd_torch" else ts
        real = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, _f=real, _n=name, **k: calls.append(_n) or _f(*a, **k))
    n = len(room)  # a calibrated copy: the predicted exposure runs, with gains and biases that differ per frame
    calib = PhotometricCalib(tuple(room.frame_ids), np.repeat(np.linspace(0.8, 1.2, n)[:, None], 3, 1),
                             np.repeat(np.linspace(-4.0, 4.0, n)[:, None], 3, 1))
    calibrated = dataclasses.replace(room, photometric=calib)
    for scene, cfg in ((room, RenderConfig()), (calibrated, RenderConfig()),
                       (room, RenderConfig(fill_method="pushpull", hole_dilation_px=3, fixed_views=3))):
        for T in (look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4)), look_at((0.5, -0.6, 1.0), (0.0, 0.5, 0.4))):
            rn = Renderer(scene, cfg, PerfConfig(backend="numba"))
            rt = Renderer(scene, cfg, PerfConfig(backend="torch", torch_device="cpu"))
            a, b = rn.render(T, K), rt.render(T, K)
            assert rn.last.views == rt.last.views and rn.last.hole_frac_per_view == rt.last.hole_frac_per_view
            assert np.array_equal(a.valid, b.valid) and np.array_equal(a.source_view, b.source_view)
            assert 0 < (~a.valid).mean() < 0.1
            # the fill's float32 order (test_pushpull_matches_numba), one level through an exposure gain <= 1.2
            # up to 2; covered pixels equal
            assert np.abs(a.depth_m - b.depth_m).max() < 1e-5
            tol = 2 if scene is calibrated else 1
            assert np.abs(a.color.astype(int) - b.color).max() <= tol and (a.color != b.color).mean() < 0.01
            assert np.array_equal(a.color[a.valid], b.color[b.valid])
    Renderer(room, RenderConfig(blend=True), PerfConfig(backend="torch", torch_device="cpu")).render(T, K)
    assert set(calls) == set(names)


def test_numba_backend_does_not_import_torch(room):
    code = ("import sys\nfrom presim.geometry import Intrinsics, look_at\nfrom presim.testing import rect_scene as S\n"
            "from presim.synthesis.renderer import Renderer, RenderConfig\nK = Intrinsics.from_fov(32, 24, 60.0)\n"
            "Renderer(S.make_scene(S.room_rects(), S.orbit_poses(2), K), RenderConfig(blend=True)).render("
            "look_at((0.1, -1.0, 1.25), (0.0, 0.5, 0.4)), K)\nprint('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[-1] == "False"
