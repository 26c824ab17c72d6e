"""Known answers for the per-frame pipeline: final fill, hole analysis, view merge (dilation ring),
the adaptive loop with scripted views, the backends, and the one z-buffer splat."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from presim.capture.reprojection import forward_warp, nearest_pixel, zbuffer_splat
from presim.geometry import Intrinsics
from presim.synthesis.completion import CompletedPoints
from presim.synthesis.config import BACKENDS, PerfConfig, RenderConfig
from presim.synthesis.fill import fill_holes
from presim.synthesis.grids import FrameGrids, grid_pixels
from presim.synthesis.holes import analyse_hole_mask, merge_view_holes
from presim.synthesis.pipeline import NUMBA, ViewImage, Workspace, stage_kernels, synthesize_frame

H, W = 48, 64


def _hole(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    valid = np.ones((H, W), bool)
    valid[r0:r1, c0:c1] = False
    return valid


# ---- fill_holes -----------------------------------------------------------------------------------

def test_fill_constant_image_is_reproduced():
    color = np.full((H, W, 3), (10, 120, 240), np.uint8)
    depth = np.full((H, W), 1.5, np.float32)
    valid = _hole(20, 26, 30, 36)
    c, d = fill_holes(color, depth, valid, "pushpull")
    assert np.array_equal(c, color) and np.array_equal(d, depth)  # averages of one value: exact
    c, d = fill_holes(color, depth, valid, "telea")
    assert np.array_equal(d, depth)  # depth is always pull-push
    # OpenCV's Telea adds a gradient-estimate term and rounds per step: measured +-2 levels on a
    # constant image (never more than 2).
    assert np.abs(c.astype(int) - color).max() <= 2


def test_fill_linear_ramp_is_reproduced():
    u = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    v = np.arange(H, dtype=np.float32)[:, None].repeat(W, 1)
    ramp = 2 * u + v  # 0..173 grey levels
    color = np.stack([ramp, 200 - 0.5 * ramp, np.full_like(ramp, 77)], -1).astype(np.uint8)
    depth = (1.0 + 0.01 * u).astype(np.float32)  # 1 cm per pixel
    valid = _hole(20, 26, 30, 36)
    holes = ~valid
    c, d = fill_holes(color, depth, valid, "pushpull")
    # Pull-push blends pyramid averages: on a ramp the color comes back to the level (measured 0),
    # the depth within 0.25 px worth of the slope (measured 0.0022 m = 0.22 px on a 6x6 hole).
    assert np.abs(c[holes].astype(int) - color[holes]).max() <= 1
    assert np.abs(d[holes] - depth[holes]).max() < 0.0025
    c, _ = fill_holes(color, depth, valid, "telea")
    assert np.abs(c[holes].astype(int) - color[holes]).max() <= 4  # measured 4 / 3 / 2 per channel


def test_fill_switches_from_telea_to_pushpull_above_two_percent():
    rng = np.random.default_rng(0)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(1, 2, (H, W)).astype(np.float32)
    limit = int(0.02 * H * W)  # 61 of 3072 pixels
    for n_hole, expect in ((limit, "telea"), (limit + 1, "pushpull")):
        valid = np.ones(H * W, bool)
        valid[1000:1000 + n_hole] = False
        valid = valid.reshape(H, W)
        auto = fill_holes(color, depth, valid, "auto")
        want = fill_holes(color, depth, valid, expect)
        other = fill_holes(color, depth, valid, "pushpull" if expect == "telea" else "telea")
        assert np.array_equal(auto[0], want[0]) and np.array_equal(auto[1], want[1]), n_hole
        assert not np.array_equal(auto[0], other[0]), n_hole  # the two methods differ here
    # The threshold is a parameter.
    valid = _hole(0, 8, 0, 8)  # 64 px = 2.08 %
    assert np.array_equal(fill_holes(color, depth, valid, "auto", telea_max_hole_frac=0.05)[0],
                          fill_holes(color, depth, valid, "telea")[0])


@pytest.mark.parametrize("method", ["telea", "pushpull", "auto"])
def test_fill_respects_the_valid_mask(method):
    rng = np.random.default_rng(1)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(1, 2, (H, W)).astype(np.float32)
    valid = rng.random((H, W)) > 0.3
    c0, d0 = color.copy(), depth.copy()
    c, d = fill_holes(color, depth, valid, method)
    assert np.array_equal(c[valid], color[valid]) and np.array_equal(d[valid], depth[valid])
    assert (d[~valid] > 0).all()  # every hole got a depth from the known ones
    assert np.array_equal(color, c0) and np.array_equal(depth, d0)  # inputs untouched
    # Nothing missing / nothing known: unchanged copies.
    for mask in (np.ones((H, W), bool), np.zeros((H, W), bool)):
        c, d = fill_holes(color, depth, mask, method)
        assert np.array_equal(c, color) and c is not color and np.array_equal(d, depth)
    with pytest.raises(ValueError, match="fill method"):
        fill_holes(color, depth, valid, "nope")


def analyse_holes(valid, *args, **kw):
    """analyse_hole_mask of a coverage mask (bool, or 0 = hole)."""
    holes = (~valid).view(np.uint8) if valid.dtype == np.bool_ else (valid == 0).astype(np.uint8)
    return analyse_hole_mask(holes, int(holes.sum()), *args, **kw)


# ---- analyse_holes ----------------------------------------------------------------------------------

def test_analyse_holes_components_big_mask_and_dilation_ring():
    valid = np.ones((H, W), bool)
    valid[10:15, 20:25] = False  # 25 px: big (>= 16)
    valid[30:32, 40:42] = False  # 4 px: small
    hs = analyse_holes(valid, big_hole_px=16, hole_dilation_px=2)
    assert hs.hole_frac == pytest.approx(29 / (H * W))
    assert hs.largest_hole_px == 25
    big = np.zeros((H, W), bool)
    big[10:15, 20:25] = True
    assert np.array_equal(hs.big, big)
    # The 5x5 elliptic kernel (radius 2) is a plus-shaped disc: 3 full middle rows, one pixel
    # above and below. Dilating the 5x5 square by it gives the 9x9 square without the two pixels
    # at each end of its top and bottom rows: 81 - 8 = 73 pixels; the small hole is not dilated.
    ring = np.zeros((H, W), bool)
    ring[8:17, 18:27] = True
    ring[[8, 8, 8, 8, 16, 16, 16, 16], [18, 19, 25, 26, 18, 19, 25, 26]] = False
    assert ring.sum() == 73
    assert np.array_equal(hs.replace, ring | ~valid)
    assert hs.replace.sum() == 73 + 4
    # No dilation: the replace mask is the holes themselves.
    assert np.array_equal(analyse_holes(valid, 16, 0).replace, ~valid)
    # Raising big_hole_px above 25 makes no hole big: nothing is dilated.
    hs = analyse_holes(valid, big_hole_px=26, hole_dilation_px=2)
    assert not hs.big.any() and np.array_equal(hs.replace, ~valid)


def test_analyse_holes_shortcuts():
    full = np.ones((H, W), bool)
    hs = analyse_holes(full)
    assert (hs.hole_frac, hs.largest_hole_px) == (0.0, 0) and not hs.replace.any()
    valid = _hole(0, 2, 0, 3)  # 6 px
    hs = analyse_holes(valid, want_replace=False)
    assert hs.largest_hole_px == 6 and hs.replace is None and hs.big is None
    # All holes together below stop_px: components are skipped, the bound is reported.
    hs = analyse_holes(valid, stop_px=6.0)
    assert hs.largest_hole_px == 6 and hs.replace is None
    # Two 3-px holes touching diagonally are one 8-connected hole.
    valid = np.ones((H, W), bool)
    valid[5, 5:8] = False
    valid[6, 8:11] = False
    assert analyse_holes(valid).largest_hole_px == 6
    # uint8 coverage (non-zero = valid) gives the same answer as bool.
    assert analyse_holes(valid.astype(np.uint8)).largest_hole_px == 6


# ---- merge_view_holes -------------------------------------------------------------------------------------

def test_merge_view_holes_writes_only_replaceable_pixels_the_view_covers():
    acc_d = np.full((H, W), 2.0, np.float32)
    acc_c = np.full((H, W, 3), 50, np.uint8)
    acc_s = np.full((H, W), 3, np.int32)
    acc_d[10:15, 20:25] = 0  # a big hole of the first view
    acc_c[10:15, 20:25] = 0
    acc_s[10:15, 20:25] = -1
    replace = analyse_holes(acc_d > 0, 16, 2).replace
    d = np.full((H, W), 1.0, np.float32)
    c = np.full((H, W, 3), 200, np.uint8)
    d[12, 22] = 0  # the second view misses one hole pixel
    before = acc_d.copy(), acc_c.copy(), acc_s.copy()
    holes = np.full((H, W), 7, np.uint8)  # scratch: rewritten whole
    n_hole = merge_view_holes(acc_d, acc_c, acc_s, replace, d, c, 7, holes)
    took = replace & (d > 0)
    assert took.sum() == 73 - 1  # the hole (minus one pixel) and its dilation ring
    assert (acc_d[took] == 1.0).all() and (acc_c[took] == 200).all() and (acc_s[took] == 7).all()
    keep = ~took
    assert np.array_equal(acc_d[keep], before[0][keep]) and np.array_equal(acc_c[keep], before[1][keep])
    assert np.array_equal(acc_s[keep], before[2][keep])
    assert acc_d[12, 22] == 0 and acc_s[12, 22] == -1
    # The ring replaced pixels the first view had (ghost contours): 2 px around the hole.
    ring = replace & (before[0] > 0)
    assert ring.sum() == 73 - 25 and (acc_s[ring] == 7).all()
    # The hole mask after the merge: the one pixel no view covers.
    assert n_hole == 1 and np.array_equal(holes, (acc_d <= 0).astype(np.uint8))


# ---- the adaptive loop with scripted views ----------------------------------------------------------

K8 = Intrinsics(fx=8.0, fy=8.0, cx=3.5, cy=3.5, width=8, height=8)


def _cfg(**kw) -> RenderConfig:
    """The loop's knobs; no view gain threshold, forward colour (the scripted views have no images)."""
    return RenderConfig(**{"min_view_gain": 0.0, "backward_color": False, **kw})


class _Views:
    """A FrameViews test double: scripted view images; the next view by FrameGrids.next_view over
    the given grids (identity target pose, K8; each grid point stands for ``z_src(v)^2`` target
    pixels at stride 1)."""

    kernels = NUMBA
    smooth_sigma_px = 0.0

    def __init__(self, candidates, images, grids, calls=None, z_src=None, near_m=0.01):
        self.candidates = list(candidates)
        self.ring_ids: list[int] = []
        self.completed: list = []
        self.images, self.calls, self.near_m = images, calls if calls is not None else [], near_m
        self.grids = FrameGrids(np.eye(4), K8, grids.__getitem__)
        self._grid = grids
        self._z = z_src or {}
        self.masks: list[int] = []  # big-hole pixels of each next_view call

    def view_image(self, view_id, replace):
        self.calls.append((view_id, None if replace is None else replace.copy()))
        d, c = self.images[view_id]
        return ViewImage(d.copy(), c.copy())

    def next_view(self, pending, big_flat, need_px, frac):
        self.masks.append(int(big_flat.sum()))
        return self.grids.next_view(pending, big_flat, self.z_src, lambda v: K8.fx, self.near_m, 1.0, need_px, frac)

    def z_src(self, v):
        return np.full(len(self._grid[v]), self._z.get(v, 1.0), np.float32)

    def blend(self, warped, color, depth_m, source):
        raise AssertionError("blend is off")

    def sources(self, warped):
        raise AssertionError("backward colour is off")

    def exposure(self, source):
        return None  # no photometric calibration: the working exposure

    def completed_points(self, warped):
        return list(self.completed)  # none by default: no completed depth

    def ring(self):
        return list(self.ring_ids)


def _grid_at(pixels: list[tuple[int, int]]) -> np.ndarray:
    """World points (identity target pose) that project onto the given (u, v) pixels of K8 at z = 1."""
    return np.array([[(u - K8.cx) / K8.fx, (v - K8.cy) / K8.fy, 1.0] for u, v in pixels], np.float32)


def test_synthesize_frame_adaptive_loop_order_and_stop():
    d0 = np.ones((8, 8), np.float32)
    d0[:, 4:] = 0  # view 10 covers the left half
    c0 = np.zeros((8, 8, 3), np.uint8)
    c0[d0 > 0] = 10
    d1 = np.full((8, 8), 2.0, np.float32)  # views 11 and 12 cover everything
    c1 = np.full((8, 8, 3), 20, np.uint8)
    images = {10: (d0, c0), 11: (d1, c1), 12: (d1 * 1.5, c1 + 5), 13: (d1, c1)}
    grids = {10: _grid_at([(0, 0)]), 11: _grid_at([(1, 1)]),  # 11 cannot reach the hole
             12: _grid_at([(5, 5), (6, 6)]), 13: _grid_at([(6, 1)])}
    calls: list = []
    cfg = _cfg(big_hole_px=4, hole_dilation_px=0, stop_hole_frac=0.0, fill_holes=False)
    res = synthesize_frame(_Views([10, 11, 12, 13], images, grids, calls), np.eye(4), K8, cfg)
    # 10 first (whole image), then the first candidate whose grid lands in the big hole: 12 (11 is
    # skipped over, 13 would also do but comes later). After 12 there is no hole: stop.
    assert res.views == [10, 12] and res.skipped == []
    assert [v for v, _ in calls] == [10, 12]
    assert calls[0][1] is None and np.array_equal(calls[1][1], d0 == 0)  # replace = the hole
    assert res.hole_frac_per_view == [0.5, 0.0] and res.hole_frac == 0.0
    assert np.array_equal(res.source_view, np.where(d0 > 0, 10, 12))
    assert np.array_equal(res.depth_m, np.where(d0 > 0, 1.0, 3.0).astype(np.float32))
    assert np.array_equal(res.color[..., 0], np.where(d0 > 0, 10, 25))  # each pixel from its view
    # greedy (next_view_fill_frac = 1): 12 puts 2 grid points into the hole, 13 puts 0 -> 12.
    calls.clear()
    res = synthesize_frame(_Views([10, 13, 12], images, grids, calls), np.eye(4), K8,
                           _cfg(big_hole_px=4, hole_dilation_px=0, stop_hole_frac=0.0, next_view_fill_frac=1.0))
    assert res.views == [10, 12]


def test_synthesize_frame_min_view_gain_known_answer():
    """Diminishing returns: a candidate is warped only when the target pixels its grid points in big
    holes stand for reach min_view_gain x H x W (64 px here; the hole is 32 px)."""
    d0 = np.ones((8, 8), np.float32)
    d0[:, 4:] = 0
    c0 = np.zeros((8, 8, 3), np.uint8)
    d1 = np.full((8, 8), 2.0, np.float32)
    c1 = np.full((8, 8, 3), 20, np.uint8)
    images = {10: (d0, c0), 12: (d1, c1), 13: (d1, c1)}
    grids = {10: _grid_at([(0, 0)]), 12: _grid_at([(5, 5), (6, 6)]), 13: _grid_at([(6, 1)])}
    # predicted fill (target pixels of the grid points in the hole): 12: 2 x 1 px, 13: 1 x 10 px
    z_src = {13: float(np.sqrt(10.0))}
    cfg = _cfg(big_hole_px=4, hole_dilation_px=0, stop_hole_frac=0.0, fill_holes=False)
    seen = []

    def run(gain):
        views = _Views([10, 12, 13], images, grids, z_src=z_src)
        res = synthesize_frame(views, np.eye(4), K8, dataclasses.replace(cfg, min_view_gain=gain))
        seen.extend(views.masks)
        return res
    assert run(0.0).views == [10, 12]  # off: the first candidate that lands in the hole
    assert run(0.03).views == [10, 12]  # need 1.92 px: 12's 2 px are enough
    assert run(0.1).views == [10, 13]  # need 6.4 px: 12 (2 px) is passed over, 13 (10 px) taken
    res = run(0.2)  # need 12.8 px: nobody -> stop, the hole stays
    assert res.views == [10] and res.skipped == [12, 13] and res.hole_frac == 0.5
    assert seen and all(n == 32 for n in seen)  # asked with the big-hole mask (the right half)
    with pytest.raises(ValueError, match="min_view_gain"):
        RenderConfig(min_view_gain=1.0)


def test_synthesize_frame_draws_the_ring_only_for_holes_the_local_group_leaves():
    """Views beyond the local group (``hole_candidates``) come after all of its own views, and only into big
    holes: the local group's 10 leaves the right half empty, its 11 cannot reach it, the ring's 20 can. A ring view
    must be predicted to fill ``ring_min_hole_frac`` of the image (32 px here): 20's one grid point stands for 40."""
    d0 = np.ones((8, 8), np.float32)
    d0[:, 4:] = 0
    c0 = np.full((8, 8, 3), 10, np.uint8)
    c0[d0 == 0] = 0
    d1 = np.full((8, 8), 2.0, np.float32)
    images = {10: (d0, c0), 11: (d0, c0), 20: (d1, np.full((8, 8, 3), 30, np.uint8))}
    grids = {10: _grid_at([(0, 0)]), 11: _grid_at([(1, 1)]), 20: _grid_at([(5, 5)])}
    cfg = _cfg(big_hole_px=4, hole_dilation_px=0, stop_hole_frac=0.0, fill_holes=False, ring_min_hole_frac=0.5)
    views = _Views([10, 11], images, grids, z_src={20: float(np.sqrt(40.0))})
    assert synthesize_frame(views, np.eye(4), K8, cfg).views == [10]  # no ring: the hole stays
    views.ring_ids = [20]
    assert synthesize_frame(views, np.eye(4), K8, cfg).views == [10]  # the ring needs the completion stage
    views.completed = [CompletedPoints(10, np.array([[0.0, 0.0, -1.0]], np.float32), np.zeros((1, 3), np.uint8))]
    calls: list = []
    views.calls = calls
    res = synthesize_frame(views, np.eye(4), K8, cfg)  # completion ran (its one point lies behind the camera)
    assert res.views == [10, 20] and res.hole_frac == 0.0 and not res.completed.any()
    assert np.array_equal(calls[1][1], d0 == 0)  # the ring's view wrote the hole only
    assert np.array_equal(res.source_view, np.where(d0 > 0, 10, 20))
    assert np.array_equal(res.color[..., 0], np.where(d0 > 0, 10, 30))
    # a fixed view count never draws the ring, nor does a hole smaller than ring_min_hole_frac (32 px < 33)
    assert synthesize_frame(views, np.eye(4), K8, dataclasses.replace(cfg, fixed_views=1)).views == [10]
    assert synthesize_frame(views, np.eye(4), K8, dataclasses.replace(cfg, ring_min_hole_frac=0.51)).views == [10]
    views = _Views([10, 11], images, grids, z_src={20: float(np.sqrt(30.0))})  # predicted 30 px < 32: passed over
    views.ring_ids = [20]
    views.completed = [CompletedPoints(10, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8))]
    res = synthesize_frame(views, np.eye(4), K8, cfg)
    assert res.views == [10] and res.skipped == [11, 20]


def test_synthesize_frame_stops_when_no_candidate_can_fill_and_fixed_views():
    d0 = np.ones((8, 8), np.float32)
    d0[:, 4:] = 0
    c0 = np.full((8, 8, 3), 9, np.uint8)
    c0[d0 == 0] = 0  # empty pixels are black, as every backend returns them
    images = {1: (d0, c0), 2: (d0, c0), 3: (d0, c0)}
    grids = {i: _grid_at([(0, 0)]) for i in images}  # nobody lands in the right half
    calls: list = []
    cfg = _cfg(big_hole_px=4, hole_dilation_px=0, stop_hole_frac=0.0, fill_holes=False)
    res = synthesize_frame(_Views([1, 2, 3], images, grids, calls), np.eye(4), K8, cfg)
    assert res.views == [1] and res.skipped == [2, 3] and res.hole_frac == 0.5
    assert (res.color[:, 4:] == 0).all() and not res.valid[:, 4:].any()
    # fixed_views = 2 warps the first two whatever they add; max_views bounds the adaptive pool.
    res = synthesize_frame(_Views([3, 1, 2], images, grids), np.eye(4), K8, _cfg(fixed_views=2, fill_holes=False))
    assert res.views == [3, 1] and res.skipped == []
    res = synthesize_frame(_Views([3, 1, 2], images, grids), np.eye(4), K8, _cfg(max_views=1, fill_holes=False))
    assert res.views == [3]
    # With filling on, the uncovered half gets a color/depth but stays invalid.
    res = synthesize_frame(_Views([1], images, grids), np.eye(4), K8, _cfg())
    assert (res.depth_m > 0).all() and not res.valid[:, 4:].any() and res.hole_frac == 0.5
    # No candidate at all: an empty (filled-with-nothing) frame.
    res = synthesize_frame(_Views([], images, grids), np.eye(4), K8, _cfg())
    assert res.views == [] and res.hole_frac == 1.0 and not res.color.any()
    assert (res.source_view == -1).all() and not res.valid.any() and not res.depth_m.any()


def test_grid_pixels_uses_the_pixel_centre_rule():
    pts = np.array([[(2.5 - K8.cx) / K8.fx, 0.0, 1.0],   # u = 2.5 -> pixel 3 (halves round up)
                    [(-0.5 - K8.cx) / K8.fx, 0.0, 1.0],  # u = -0.5 -> pixel 0
                    [(7.5 - K8.cx) / K8.fx, 0.0, 1.0],   # u = 7.5 -> pixel 8: outside
                    [0.0, 0.0, 0.005]], np.float32)       # nearer than near_m: dropped
    v = int(np.floor(K8.cy + 0.5))
    assert grid_pixels(pts, np.eye(4), K8, 0.01).tolist() == [v * 8 + 3, v * 8 + 0]


# ---- backends ---------------------------------------------------------------------------------------

def test_backends_are_the_perf_configs():
    assert BACKENDS == ("numba", "reference", "torch")
    for name in BACKENDS:
        assert PerfConfig(backend=name).backend == name
    for name in ("cuda", "torch_batch"):
        with pytest.raises(ValueError, match="backend must be one of"):
            PerfConfig(backend=name)


def test_backends_share_one_signature_and_agree_on_a_plane():
    from presim.synthesis.warp import prepare_view

    K = Intrinsics(fx=20.0, fy=20.0, cx=11.5, cy=8.5, width=24, height=18)
    rng = np.random.default_rng(2)
    color = rng.integers(0, 256, (18, 24, 3), dtype=np.uint8)
    depth = np.full((18, 24), 2.0, np.float32)
    depth[5:12, 6:14] = 1.0
    view = prepare_view(color, depth, K, np.eye(4), 4)
    T = np.eye(4)
    T[0, 3] = 0.03
    cfg = RenderConfig()
    outs = {}
    for name in BACKENDS:
        v = view
        if name == "torch":
            try:
                from presim.synthesis import torch_kernels
            except ImportError:  # torch is an optional group
                continue
            v = torch_kernels.to_device(view, "cpu")
        outs[name] = stage_kernels(name).view_image(v, T, K, cfg, None, Workspace())
    ref = outs["reference"]
    for name, img in outs.items():
        assert img.depth_m.dtype == np.float32 and img.color.dtype == np.uint8
        # float32 (+ fastmath) vs float64 projection: a projection within ~1e-5 px of a pixel
        # border may land one pixel over; on this 432-px image none does.
        assert np.array_equal(img.depth_m, ref.depth_m), name
        assert np.array_equal(img.color, ref.color), name


# ---- the one z-buffer splat ---------------------------------------------------------------------------

def test_zbuffer_splat_rules():
    uv = np.array([[0.49, 0.0],    # -> pixel (0, 0)
                   [0.5, 0.0],     # half rounds up -> (1, 0)
                   [1.49, 0.2],    # -> (1, 0), nearer: wins over point 1
                   [1.0, 0.0],     # -> (1, 0), same depth as point 2: later, loses the tie
                   [2.5, 1.5],     # -> (3, 2): outside a 3-wide image
                   [-0.5, -0.5],   # -> (0, 0) by the centre rule, but behind near: dropped
                   [np.nan, 0.0],  # not finite: dropped
                   [1.5, 1.4999]], np.float64)  # -> (2, 1)
    z = np.array([1.0, 2.0, 1.5, 1.5, 1.0, 0.005, 1.0, 3.0])
    lin, win = zbuffer_splat(uv, z, 3, 2, near_m=0.01)
    assert lin.tolist() == [0, 1, 5] and win.tolist() == [0, 2, 7]
    ui, vi, inside = nearest_pixel(uv, 3, 2)
    assert inside.tolist() == [True, True, True, True, False, True, False, True]
    assert ui[inside].tolist() == [0, 1, 1, 1, 0, 2] and vi[inside].tolist() == [0, 0, 0, 0, 0, 1]


def test_forward_warp_rounds_half_pixels_up():
    # A 2 px wide image shifted by exactly half a pixel: with floor(u + 0.5) both pixels move one to
    # the right (np.rint would have sent u = 0.5 to 0 and u = 1.5 to 2, splitting them).
    K = Intrinsics(fx=10.0, fy=10.0, cx=0.5, cy=0.0, width=2, height=1)
    color = np.array([[[10, 10, 10], [20, 20, 20]]], np.uint8)
    depth = np.ones((1, 2), np.float32)
    T = np.eye(4)
    T[0, 3] = 0.05  # x + 0.05 m at z = 1 m -> u + 0.5 px
    c, d = forward_warp(color, depth, K, K, T)
    assert d.tolist() == [[0.0, 1.0]] and c[0, 1].tolist() == [10, 10, 10]


def test_synthesis_imports_nothing_above_capture():
    # Layering: geometry -> capture/imaging -> photometric/depth -> synthesis; synthesis needs no depth (the
    # evaluation, which refines depth, lives in presim.evaluation) and of photometric only apply.py.
    import subprocess
    import sys

    code = ("import sys, importlib\n"
            "for m in ('pipeline', 'execution', 'renderer', 'select', 'warp', 'cracks', 'holes', 'fill',\n"
            "          'kernels_reference'):\n"
            "    importlib.import_module('presim.synthesis.' + m)\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('presim.'))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    # presim.runtime is the package's own import-time process setup (imported by presim/__init__).
    allowed = ("capture", "geometry", "imaging", "io_utils", "lru", "numba_threads", "sensors", "synthesis", "runtime")
    assert out and not [m for m in out if m.split(".")[1] not in allowed
                        and m not in ("presim.photometric", "presim.photometric.apply")], out


@pytest.mark.parametrize("shape,known_frac", [((8, 10), 0.3), ((30, 42), 0.05), ((48, 64), 0.9), ((31, 41), 0.4)])
def test_numba_pushpull_matches_reference_pushpull(shape, known_frac):
    """The numba full-size steps against pushpull_fill (the OpenCV version, the reference): sparse
    and dense known pixels; an odd size takes pushpull_fill itself."""
    from presim.imaging.pushpull import pushpull_fill, pushpull_rgbd

    rng = np.random.default_rng(shape[0])
    color = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    depth = rng.uniform(1, 2, shape).astype(np.float32)
    valid = rng.random(shape) < known_frac
    valid.flat[0] = True
    c, d = pushpull_rgbd(color, depth, valid)
    ref = pushpull_fill(np.concatenate([color.astype(np.float32), depth[..., None]], -1), valid)
    np.testing.assert_array_equal(c[valid], color[valid])
    np.testing.assert_array_equal(d[valid], depth[valid])
    # float32 bilinear weights computed differently: measured <= 1e-6 m; colour rounding may flip
    # one level where a value sits within float error of .5.
    assert np.abs(d - ref[..., 3]).max() < 1e-5
    ref_c = np.clip(ref[..., :3] + 0.5, 0, 255).astype(np.uint8)
    assert np.abs(c.astype(int) - ref_c).max() <= 1
    assert np.mean(c != ref_c) < 0.01
    _, d_only = pushpull_rgbd(None, depth, valid)
    assert np.abs(d_only - d).max() < 1e-5


@pytest.mark.parametrize("with_color", [True, False])
def test_pull0_kernel_is_the_exact_mean_of_known_children(with_color):
    """Level 0 -> 1 of the numba pull-push: the 2x2 means of the known children (float32 sums in
    row order, weights = known count / 4), exactly, whatever the unknown pixels hold (0, NaN, inf,
    negative: they must not leak into the sums)."""
    from presim.imaging.pushpull import _pull0_kernel

    rng = np.random.default_rng(7)
    H, W = 34, 46
    known = rng.random((H, W)) < 0.6
    depth = rng.uniform(0.2, 4.0, (H, W)).astype(np.float32)
    depth[~known] = rng.choice(np.array([0.0, np.nan, np.inf, -2.0], np.float32), int((~known).sum()))
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    C = 4 if with_color else 1
    acc = np.full((H // 2, W // 2, C), -1.0, np.float32)
    w = np.full((H // 2, W // 2), -1.0, np.float32)
    _pull0_kernel(color if with_color else np.zeros((1, 1, 3), np.uint8), depth, known, with_color, acc, w)
    children = [(0, 0), (0, 1), (1, 0), (1, 1)]
    sw = np.zeros((H // 2, W // 2), np.float32)
    sd = np.zeros((H // 2, W // 2), np.float32)
    sc = np.zeros((H // 2, W // 2, 3), np.float32)
    for dy, dx in children:  # the same float32 additions, in the same order, numpy
        k = known[dy::2, dx::2]
        sw = sw + np.where(k, np.float32(1), np.float32(0))
        sd = sd + np.where(k, depth[dy::2, dx::2], np.float32(0))
        sc = sc + np.where(k[..., None], color[dy::2, dx::2].astype(np.float32), np.float32(0))
    np.testing.assert_array_equal(w, sw * np.float32(0.25))
    np.testing.assert_array_equal(acc[..., C - 1], sd * np.float32(0.25))
    if with_color:
        np.testing.assert_array_equal(acc[..., :3], sc * np.float32(0.25))
    assert np.isfinite(acc).all()


def test_numba_and_reference_pushpull_agree_on_a_ramp():
    """The numba fill and its reference (pushpull_fill) reproduce a linear ramp inside a hole the
    same way (the pyramids differ only at odd sizes)."""
    from presim.imaging.pushpull import pushpull_fill

    u = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    color = np.stack([2 * u, 200 - u, np.full_like(u, 77)], -1).astype(np.uint8)
    depth = (1.0 + 0.01 * u).astype(np.float32)
    valid = _hole(20, 26, 30, 36)
    cn, dn = fill_holes(color, depth, valid, "pushpull")
    both = pushpull_fill(np.concatenate([color.astype(np.float32), depth[..., None]], -1), valid)
    co, do = np.clip(both[..., :3] + 0.5, 0, 255).astype(np.uint8), both[..., 3]
    holes = ~valid
    assert np.abs(cn[holes].astype(int) - co[holes]).max() <= 1
    assert np.abs(dn[holes] - do[holes]).max() < 1e-3


@pytest.mark.parametrize("seed,hole_frac,shape", [(0, 0.1, (H, W)), (1, 0.45, (H, W)), (2, 0.7, (H, W)),
                                                   (3, 0.3, (37, 50)), (4, 0.05, (8, 8))])
def test_analyse_holes_matches_scipy_labelling(seed, hole_frac, shape):
    """Largest hole, big mask and replace mask against scipy's 8-connected labelling + dilation
    (widths that are multiples of 8, read 8 pixels at a time, and one that is not)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    holes = ndimage.binary_opening(rng.random(shape) < hole_frac) | (rng.random(shape) < 0.02)
    valid = ~holes
    hs = analyse_holes(valid, big_hole_px=16, hole_dilation_px=2)
    lab, n = ndimage.label(holes, structure=np.ones((3, 3)))
    areas = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    assert hs.largest_hole_px == areas.max()
    big = np.isin(lab, 1 + np.flatnonzero(areas >= 16))
    np.testing.assert_array_equal(hs.big, big)
    disk = np.ones((5, 5), bool)  # OpenCV's 5x5 ellipse: the full square without 4 corner pairs
    disk[[0, 0, 4, 4], [0, 1, 0, 1]] = disk[[0, 0, 4, 4], [3, 4, 3, 4]] = False
    np.testing.assert_array_equal(hs.replace, holes | ndimage.binary_dilation(big, disk))
    last = analyse_holes(valid, want_replace=False, want_largest=False)
    assert last.hole_frac == hs.hole_frac and last.replace is None
    for r in (0, 1, 3, 5):  # other radii: the kernel's dilation = OpenCV's ellipse (as before it)
        se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        want = holes | ndimage.binary_dilation(big, se.astype(bool)) if r else holes
        np.testing.assert_array_equal(analyse_holes(valid, 16, r).replace, want)


@pytest.mark.parametrize("C", [1, 4])
def test_fill_push_step_kernel_equals_numpy_expression_exactly(C):
    """One push step of the numba pull-push = pushpull_fill's numpy expression, bit for bit
    (weights 0, fractional, 1; values from a real-like range)."""
    from presim.imaging.pushpull import _blend_level_kernel

    rng = np.random.default_rng(C)
    h, w = 31, 47
    wl = rng.choice([0.0, 0.25, 0.5, 0.75, 1.0], (h, w)).astype(np.float32) * rng.random((h, w)).astype(np.float32)
    wl[::3] = rng.choice([0.0, 1.0, 0.25], (len(range(0, h, 3)), w)).astype(np.float32)
    acc = (rng.random((h, w, C)) * 255 * wl[..., None]).astype(np.float32)
    up = (rng.random((h, w, C)) * 255).astype(np.float32)
    alpha = np.clip(wl, 0.0, 1.0)[..., None]
    want = acc / np.maximum(wl, 1e-12)[..., None] * alpha + up * (1.0 - alpha)
    got = np.empty_like(up)
    _blend_level_kernel(acc, wl, up, got)
    assert got.dtype == want.dtype == np.float32
    np.testing.assert_array_equal(got, want)
