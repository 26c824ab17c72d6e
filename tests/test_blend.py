"""Multi-view blending (presim/synthesis/blend.py, RenderConfig.blend)."""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics, look_at
from presim.imaging.feather import coverage_counts, feather_box, feather_map
from presim.synthesis.blend import BlendConfig, BlendInput, blend_numba, blend_reference
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S

K = Intrinsics.from_fov(160, 120, 60.0)


def _plane_scene(checker_m: float):
    poses = np.stack([look_at((x, 0.0, 0.0), (x, 0.0, 2.0), up=(0, -1, 0)) for x in (-0.1, 0.1)])
    return S.make_scene(S.plane_rects(2.0, checker_m=checker_m), poses, K)


def test_two_views_of_a_flat_coloured_plane_blend_to_that_colour_exactly():
    sc = _plane_scene(0.0)
    colour = sc.frames.load(0)[0][60, 80]
    assert np.array_equal(sc.frames.load(1)[0][60, 80], colour)
    T = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 2.0), up=(0, -1, 0))
    r = Renderer(sc, RenderConfig(blend=True, fixed_views=2))
    out = r.render(T, K)
    assert r.last.views == [0, 1] and r.last.ms["blend"] > 0
    assert np.array_equal(out.color[out.valid], np.broadcast_to(colour, out.color[out.valid].shape))
    assert out.valid.mean() > 0.95


def _inputs(seed: int = 0):
    """Random loop result + 3 candidate views with agreeing / disagreeing depths."""
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


def test_numba_matches_reference():
    inp, Kt = _inputs()
    T = look_at((0.0, 0.0, 0.0), (0.1, 0.0, 2.0))
    cfg = BlendConfig(depth_tol_rel=0.02, feather_px=4.0)
    a = blend_numba(inp, Kt, T, cfg).astype(int)
    b = blend_reference(inp, Kt, T, cfg).astype(int)
    assert np.abs(a - b).max() <= 1 and (a != b).mean() < 0.01  # .5-level rounding in float order
    # Pixels with a single agreeing candidate keep the winner's colour; uncovered pixels are untouched.
    assert np.array_equal(a[:3], inp.color[:3].astype(int))
    assert (a != inp.color).any()


def test_views_behind_the_front_surface_are_not_blended():
    inp, Kt = _inputs(1)
    vd = inp.view_depth_m.copy()
    vd[1:] = inp.depth_m * 1.3  # views 7 and 9 see a surface 30 % farther than the winner (view 4)
    far = BlendInput(inp.color, inp.depth_m, np.full_like(inp.source, 4), inp.view_ids, vd,
                     inp.view_color, inp.centres, inp.quality)
    out = blend_numba(far, Kt, look_at((0.0, 0.0, 0.0), (0.0, 0.0, 2.0)), BlendConfig())
    assert np.array_equal(out, inp.color)


def test_feather_counts_give_feather_map_exactly():
    """The kernel's feathering (integer box counts, scaled as OpenCV's float box filter scales
    them) equals feather_map bit for bit, for every box size up to 15 px and at image borders."""

    rng = np.random.default_rng(3)
    depth = np.where(rng.random((50, 70)) < 0.6, rng.uniform(0.5, 2.0, (50, 70)), 0).astype(np.float32)
    depth[10:30, 20:50] = 1.0  # a solid block: counts from 0 to the full box
    for px in (1.0, 3.0, 4.0, 8.0, 11.0, 15.0):
        k = feather_box(px)
        cnt = coverage_counts(depth, px).astype(np.float64)
        scale = 1.0 if px <= 1 else 1.0 / (k * k)
        m = (cnt * scale).astype(np.float32)
        f = np.where(depth > 0, np.clip(np.float32(2.0) * m - np.float32(1.0), 0.0, 1.0), 0.0).astype(np.float32)
        assert np.array_equal(f, feather_map(depth, px)), px
    assert coverage_counts(depth, 8.0).max() == 81


def test_numba_planar_and_interleaved_view_colours_agree():
    inp, Kt = _inputs(2)
    T = look_at((0.0, 0.0, 0.0), (0.1, 0.0, 2.0))
    planar = np.ascontiguousarray(inp.view_color.transpose(0, 3, 1, 2)).transpose(0, 2, 3, 1)
    a = blend_numba(inp, Kt, T, BlendConfig(feather_px=4.0))
    b = blend_numba(inp._replace(view_color=planar), Kt, T, BlendConfig(feather_px=4.0))
    assert np.array_equal(a, b)


def test_blend_config_and_render_config_checks():
    with pytest.raises(ValueError):
        BlendConfig(max_views=0)
    with pytest.raises(ValueError, match="blend_depth_tol"):
        RenderConfig(blend_depth_tol=0.0)


def test_blending_reduces_noise_on_the_room():
    """Independent per-view colour noise averages out: blended error < winner-takes-all error (the
    winner's forward colour, as the thesis; the backward colour's bilinear taps average some noise
    themselves)."""
    Kr = Intrinsics.from_fov(160, 120, 60.0)
    poses = S.orbit_poses(5, span_m=0.4)
    clean = S.make_scene(S.room_rects(), poses, Kr)
    rng = np.random.default_rng(0)
    noisy_col = np.clip(clean.frames.color.astype(int) + rng.normal(0, 12, clean.frames.color.shape).round(),
                        0, 255).astype(np.uint8)
    from dataclasses import replace

    from presim.capture.scene import ArrayFrameSource

    noisy = replace(clean, frames=ArrayFrameSource(noisy_col, clean.frames.depth_m))
    k = 2
    others = noisy.subset([0, 1, 3, 4])
    truth = clean.frames.load(k)[0].astype(float)
    errs = []
    for blend in (False, True):
        out = Renderer(others, RenderConfig(blend=blend, fixed_views=3, backward_color=False)).render(poses[k], Kr)
        errs.append(np.sqrt(np.mean((out.color[out.valid] - truth[out.valid]) ** 2)))
    assert errs[1] < 0.85 * errs[0]


def test_front_surface_kernels_match_their_references():
    """front_of_layers = per-pixel smallest depth over the layers (numpy) = the warp kernel with one
    layer (the one-pass z-buffer of all the view's points)."""
    from dataclasses import replace

    from presim.synthesis.blend import front_of_layers
    from presim.synthesis.warp import warp_layers

    sc = S.make_scene(S.room_rects(), S.orbit_poses(3, span_m=0.4), K)
    r = Renderer(sc, RenderConfig(lod_levels=0))
    view = r.view(0)
    T = np.linalg.inv(S.orbit_poses(3, span_m=0.4)[1])
    one = warp_layers(replace(view, layer_start=np.array([0, view.layer_start[-1]], np.int64)), T, K, 0.01)
    d, c = one.depth_m[0], one.color[0]
    assert (d > 0).mean() > 0.5
    lay = warp_layers(view, T, K, 0.01)
    d2, c2 = np.empty_like(d), np.empty_like(c)
    front_of_layers(lay.depth_m, lay.color, d2, c2)
    z = np.where(lay.depth_m > 0, lay.depth_m, np.inf)
    best = np.argmin(z, axis=0)
    ref_d = np.take_along_axis(lay.depth_m, best[None], 0)[0]
    ref_c = np.take_along_axis(lay.color, best[None, ..., None], 0)[0]
    assert np.array_equal(d2, ref_d) and np.array_equal(c2, ref_c)
    # Same surface as the one-layer z-buffer (ties broken towards the nearer layer in both).
    assert np.array_equal(d2, d) and np.array_equal(c2, c)
    # A view image writes the same front surface from the layers it warps (planar colour memory,
    # as in the blend's stacks), and its own output does not change.
    from presim.synthesis.pipeline import Workspace, view_image_numba

    d3 = np.empty_like(d)
    c3 = np.empty((3,) + d.shape, np.uint8).transpose(1, 2, 0)
    cfg = RenderConfig(lod_levels=0)
    plain = view_image_numba(view, T, K, cfg, None, Workspace())
    fused = view_image_numba(view, T, K, cfg, None, Workspace(front=(d3, c3)))
    assert np.array_equal(d3, ref_d) and np.array_equal(c3, ref_c)
    assert np.array_equal(plain.depth_m, fused.depth_m) and np.array_equal(plain.color, fused.color)


def test_blend_reuses_the_loops_warps_and_gives_the_same_image(monkeypatch):
    """With the numba backend the front surfaces of the views the loop warped are taken from its
    warps (no re-warp); the blended image equals the one with every view warped again by the blend."""
    import presim.synthesis.renderer as R

    poses = S.orbit_poses(5, span_m=0.4)
    sc = S.make_scene(S.room_rects(), poses, K)
    others = sc.subset([0, 1, 3, 4])
    rewarps = []
    front_points = R.warp_layers

    def counted(*a):
        rewarps[-1] += 1
        return front_points(*a)

    monkeypatch.setattr(R, "warp_layers", counted)
    loop_image = R._FrameViews.view_image
    outs, warped = [], []
    for reuse in (True, False):
        rewarps.append(0)
        with monkeypatch.context() as m:
            if not reuse:
                def forget(self, view_id, replace, _orig=loop_image):
                    img = _orig(self, view_id, replace)
                    self.fronts.clear()  # hide the loop's front surfaces from the blend
                    return img

                m.setattr(R._FrameViews, "view_image", forget)
            r = Renderer(others, RenderConfig(blend=True, fixed_views=2, lod_levels=0))
            outs.append(r.render(poses[2], K).color)
            warped.append(len(r.last.views))
    assert np.array_equal(outs[0], outs[1])
    assert warped == [2, 2] and rewarps[1] - rewarps[0] == 2  # the two warped views: reused, or warped again
