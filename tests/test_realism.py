"""Known answers of the realism stages (issue 42): backward colour sampling, the background-side fill,
predicted exposure."""

from __future__ import annotations

import numpy as np
import pytest

from presim.capture.calibration import PhotometricCalib
from presim.geometry import Intrinsics
from presim.photometric.apply import apply_exposure, correct_colors, predict_exposure
from presim.synthesis.fill import fill_holes, foreground_rim
from presim.synthesis.resample import SourceImage, resample_colors, resample_colors_ref, stack_sources

K = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def _plane_case(t_x: float, z: float = 2.0, seed: int = 0):
    """A fronto-parallel plane at depth z with a random texture, seen by a source camera at the origin
    and a target camera moved by t_x along x: target pixel u shows source position u + fx t / z."""
    tex = np.random.default_rng(seed).integers(0, 256, (K.height, K.width, 3), np.uint8)
    src = SourceImage(tex, np.full((K.height, K.width), z, np.float32), K, np.eye(4))
    T_world_cam = np.eye(4)
    T_world_cam[0, 3] = t_x
    depth = np.full((K.height, K.width), z, np.float32)
    source = np.full((K.height, K.width), 7, np.int32)
    return tex, stack_sources([7], [src]), T_world_cam, depth, source


@pytest.mark.parametrize("t_x", [0.0, 0.0037, 0.0123, -0.021])
def test_backward_sampling_of_a_plane_under_subpixel_motion_is_bilinear(t_x):
    tex, st, T, depth, source = _plane_case(t_x)
    start = np.zeros_like(tex)
    ref = resample_colors_ref(start, depth, source, K, T, st)
    fast = resample_colors(start, depth, source, K, T, st)
    assert np.array_equal(ref, fast)
    # the bilinear reference on paper: row v, position u + shift, linear between two columns
    u = np.arange(K.width) + K.fx * t_x / 2.0
    inside = (u >= 0) & (u <= K.width - 1)
    u0 = np.floor(u[inside]).astype(int)
    f = u[inside] - u0
    u1 = np.minimum(u0 + 1, K.width - 1)
    want = np.floor((1 - f)[None, :, None] * tex[:, u0] + f[None, :, None] * tex[:, u1] + 0.5)
    got = ref[:, inside].astype(float)
    assert np.abs(got - want).max() <= 1  # float rounding at .5 levels only
    assert (ref[:, ~inside] == 0).all()  # outside the source image: the splatted colour is kept


def test_backward_sampling_torch_equals_reference():
    torch_kernels = pytest.importorskip("presim.synthesis.torch_kernels")
    tex, st, T, depth, source = _plane_case(0.0123, seed=1)
    start = np.zeros_like(tex)
    ref = resample_colors_ref(start, depth, source, K, T, st)
    assert np.array_equal(torch_kernels.resample_colors_torch(start, depth, source, K, T, st, device="cpu"), ref)


def test_backward_sampling_skips_taps_across_a_depth_edge():
    """Source: left half near (1 m, black), right half far (3 m, white). A target pixel on the far
    surface next to the edge takes only far (white) taps."""
    color = np.zeros((K.height, K.width, 3), np.uint8)
    color[:, 32:] = 255
    d = np.full((K.height, K.width), 1.0, np.float32)
    d[:, 32:] = 3.0
    st = stack_sources([0], [SourceImage(color, d, K, np.eye(4))])
    T = np.eye(4)
    T[0, 3] = -0.5 * 3.0 / K.fx  # half a pixel to the left at 3 m: u = 32 samples source u = 31.5
    depth = np.full((K.height, K.width), 3.0, np.float32)
    source = np.zeros((K.height, K.width), np.int32)
    out = resample_colors(np.full_like(color, 7), depth, source, K, T, st)
    assert (out[:, 32] == 255).all()  # the near tap (black, 1 m) was dropped
    assert (out[:, 10] == 7).all()  # no far tap at all around u = 9.5: the splatted colour stays


def _box_on_wall(hole_w: int = 6):
    """A textured wall at 3 m, a flat red box at 1 m on the left, and a disocclusion (hole) of width
    ``hole_w`` right of the box's edge, as a target camera moving right would see."""
    rng = np.random.default_rng(3)
    H, W = 48, 64
    color = rng.integers(0, 120, (H, W, 3), np.uint8)
    color[..., 2] = rng.integers(100, 200, (H, W), np.uint8)  # the wall is bluish, never red
    depth = np.full((H, W), 3.0, np.float32)
    color[:, :24] = (255, 0, 0)  # RGB red box
    depth[:, :24] = 1.0
    valid = np.ones((H, W), bool)
    valid[:, 24:24 + hole_w] = False
    color[~valid] = 0
    depth[~valid] = 0
    return color, depth, valid


@pytest.mark.parametrize("method", ["pushpull", "telea"])
def test_disocclusion_behind_a_box_fills_with_the_wall_not_the_box(method):
    color, depth, valid = _box_on_wall()
    hole = ~valid
    red = np.array([255, 0, 0], float)

    def redness(c):
        return float(np.linalg.norm(c[hole].astype(float) - red, axis=1).mean())

    plain, _ = fill_holes(color, depth, valid, method)
    background, _ = fill_holes(color, depth, valid, method, background_rim_px=4)
    assert foreground_rim(depth, valid, 4)[:, 20:24].all()  # the box's edge is the rim
    assert redness(background) > 150  # wall colours: far from red
    near = np.zeros_like(hole)
    near[:, 24:27] = True  # the half of the hole next to the box

    def redness_near(c):
        return float(np.linalg.norm(c[near].astype(float) - red, axis=1).mean())

    assert redness_near(plain) < redness_near(background) - 10  # the plain fill pulls box colour in
    assert (background[valid] == color[valid]).all()  # known pixels never change


def _calib(gains, biases):
    n = len(gains)
    return PhotometricCalib(tuple(f"f{i}" for i in range(n)), np.asarray(gains, float).reshape(n, 3),
                            np.asarray(biases, float).reshape(n, 3))


def test_predicted_exposure_equals_the_neighbours_gain_when_they_agree():
    calib = _calib([[1.2, 0.9, 1.1]] * 3 + [[0.5, 0.5, 0.5]], [[5.0, -3.0, 2.0]] * 3 + [[0.0, 0.0, 0.0]])
    A, b = predict_exposure(calib, np.array([0, 1, 2]), np.array([10.0, 300.0, 7.0]))
    assert np.allclose(A, np.diag([1.2, 0.9, 1.1])) and np.allclose(b, [5.0, -3.0, 2.0])
    # weights decide between disagreeing neighbours; no weight: no prediction
    A2, _ = predict_exposure(calib, np.array([0, 3]), np.array([1.0, 1.0]))
    assert np.allclose(np.diag(A2), [0.85, 0.7, 0.8])
    assert predict_exposure(calib, np.array([0]), np.array([0.0])) is None


def test_apply_exposure_matches_the_colour_model_reference():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (20, 30, 3), np.uint8)
    A, b = np.diag([1.3, 0.8, 1.05]), np.array([-4.0, 6.0, 0.5])
    assert np.array_equal(apply_exposure(img, A, b), correct_colors(img, np.eye(3), np.zeros(3), A, b))
    A[0, 1] = 0.1  # a full 3x3 transform goes through the reference itself
    assert np.array_equal(apply_exposure(img, A, b), correct_colors(img, np.eye(3), np.zeros(3), A, b))


def test_renderer_gives_a_calibrated_scene_its_neighbours_exposure():
    """Every capture frame of the rectangle room taken with gain 1.25: the renderer works at the
    capture's mean exposure and hands back the frames' own exposure, so a render at a capture
    pose matches that frame (no information from any target image is used)."""
    from dataclasses import replace

    from presim.synthesis.renderer import RenderConfig, Renderer
    from presim.testing.rect_scene import make_scene, orbit_poses, room_rects

    Kc = Intrinsics.from_fov(80, 60, 70.0)
    poses = orbit_poses(6)
    scene = make_scene(room_rects(), poses, Kc)
    g = 0.8
    src = scene.frames
    src.color[:] = np.clip(np.floor(src.color.astype(float) * g + 0.5), 0, 255).astype(np.uint8)
    calib = _calib([[g] * 3] * len(scene), [[0.0] * 3] * len(scene))
    scene = replace(scene, photometric=replace(calib, frame_ids=tuple(scene.frame_ids)))
    on = Renderer(scene, RenderConfig()).render(poses[2], Kc)
    off = Renderer(scene, RenderConfig(predict_exposure=False)).render(poses[2], Kc)
    real = src.color[2].astype(float)
    err_on = np.abs(on.color.astype(float) - real)[on.valid].mean()
    err_off = np.abs(off.color.astype(float) - real)[off.valid].mean()
    assert err_on < 2.0 < err_off  # the mean exposure is 1/0.8 of the frames'
