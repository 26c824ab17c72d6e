"""Photometric calibration (presim/photometric/; its types in presim/capture/calibration.py), its storage,
and its application at render time (presim/photometric/apply.py, RenderConfig.use_photometric / exposure_frame)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from presim.capture.calibration import PhotometricCalib
from presim.photometric.apply import ViewColorTransform, apply_gain_bias, gain_bias_lut
from presim.photometric.calibrate import PhotometricConfig, calibrate_photometric, photometric_pairs
from presim.capture.scene import ArrayFrameSource, SceneError
from presim.capture.store import PHOTOMETRIC_FILE, load_scene, save_photometric, save_scene
from presim.geometry import Intrinsics
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S

# Known per-frame gains (mean 1 per channel; per-channel white-balance tilt).
GAINS = np.array([1.0, 0.85, 1.15, 0.9, 1.1, 0.95, 1.05, 1.0])
GAINS_RGB = np.stack([GAINS, GAINS * 1.02, GAINS * 0.97], axis=1)
GAINS_RGB /= GAINS_RGB.mean(axis=0)


@pytest.fixture(scope="module")
def room():
    """8 exact views of the textured room at 320x240 (radiance scaled by 0.75 so no gain clips)."""
    K = Intrinsics(320.0, 320.0, 159.5, 119.5, 320, 240)
    sc = S.make_scene(S.room_rects(), S.orbit_poses(8), K)
    radiance = sc.frames.color.astype(np.float64) * 0.75
    base = np.clip(np.floor(radiance + 0.5), 0, 255).astype(np.uint8)
    gained = np.clip(np.floor(radiance * GAINS_RGB[:, None, None, :] + 0.5), 0, 255).astype(np.uint8)
    return (dataclasses.replace(sc, frames=ArrayFrameSource(base, sc.frames.depth_m)),
            dataclasses.replace(sc, frames=ArrayFrameSource(gained, sc.frames.depth_m)))


@pytest.mark.parametrize("model", ["gain_bias", "gain"])
def test_known_gains_are_recovered_within_1_percent(room, model):
    _, gained = room
    cal = calibrate_photometric(gained, PhotometricConfig(model=model), show_progress=False)
    assert cal.gain.shape == (8, 3)
    np.testing.assert_allclose(cal.gain.mean(axis=0), 1.0, atol=1e-9)  # anchored at the mean exposure
    np.testing.assert_allclose(cal.bias.mean(axis=0), 0.0, atol=1e-6)
    assert np.abs(cal.gain / GAINS_RGB - 1.0).max() < 0.01
    assert np.abs(cal.bias).max() < (1.5 if model == "gain_bias" else 1e-12)  # true bias is 0 levels
    assert cal.stats["rms_after"][0] < cal.stats["rms_before"][0]


def test_identical_exposures_give_the_identity(room):
    base, _ = room
    # Not exactly the identity: resampling differences at texture edges leave a noise floor (~0.5 %).
    cal = calibrate_photometric(base, show_progress=False)
    np.testing.assert_allclose(cal.gain, 1.0, atol=1e-2)
    np.testing.assert_allclose(cal.bias, 0.0, atol=1.5)


def test_pairs_respect_neighbours_and_angle():
    T = S.orbit_poses(6)
    pairs = photometric_pairs(T, 1, 90.0)
    assert all(i < j for i, j in pairs) and (0, 1) in pairs and (4, 5) in pairs
    assert all(j - i == 1 for i, j in pairs)  # nearest neighbour on a line of poses
    T2 = T.copy()
    T2[3, :3, :3] = -T2[3, :3, :3] @ np.diag([1, -1, 1])  # frame 3 looks backwards (still a rotation)
    assert all(3 not in p for p in photometric_pairs(T2, 2, 45.0))


@pytest.mark.parametrize("bad_gain, bad_bias, match", [
    (np.nan, 0.0, "gains must be finite and > 0.*f1="),
    (-0.5, 0.0, "gains must be finite and > 0.*f1="),
    (0.0, 0.0, "gains must be finite and > 0"),
    (1.0, np.inf, "biases must be finite.*f1="),
])
def test_calibration_rejects_nan_or_non_positive_gains(bad_gain, bad_bias, match):
    """A gain of NaN, 0 or below (or a non-finite bias) is refused at construction, naming the frame,
    and a photometric.json holding one is refused naming the file."""
    gain, bias = np.ones((3, 3)), np.zeros((3, 3))
    gain[1, 2], bias[1, 0] = bad_gain, bad_bias
    with pytest.raises(ValueError, match=match):
        PhotometricCalib(("f0", "f1", "f2"), gain, bias)
    good = PhotometricCalib(("f0", "f1", "f2"), np.ones((3, 3)), np.zeros((3, 3))).to_json()
    good["frames"][1]["gain"][2], good["frames"][1]["bias"][0] = bad_gain, bad_bias
    with pytest.raises(ValueError, match="scene/photometric.json: malformed"):
        PhotometricCalib.from_json(good, "scene/photometric.json")


def test_lut_equals_the_float_reference():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (13, 17, 3), dtype=np.uint8)
    gv, bv, go, bo = np.array([0.8, 1.1, 1.0]), np.array([3.0, -2.0, 0.5]), np.array([1.2, 0.9, 1.0]), np.zeros(3)
    import cv2

    assert np.array_equal(cv2.LUT(img, gain_bias_lut(gv, bv, go, bo)), apply_gain_bias(img, gv, bv, go, bo))
    # Identity transform keeps every level.
    assert np.array_equal(gain_bias_lut(np.ones(3), np.zeros(3), np.ones(3), np.zeros(3))[0, :, 0], np.arange(256))


def test_clipped_black_stays_black():
    from presim.photometric.apply import apply_exposure, correct_colors

    img = np.array([[[0, 0, 0], [0, 40, 200], [10, 10, 10]]], np.uint8)
    lifted = apply_gain_bias(img, np.ones(3), np.full(3, -3.0), np.ones(3), np.zeros(3))  # bias +3 levels
    assert lifted.tolist() == [[[0, 0, 0], [0, 43, 203], [13, 13, 13]]]
    A = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    out = correct_colors(img, np.eye(3), np.zeros(3), A, np.full(3, 3.0))
    assert out[0, 0].tolist() == [0, 0, 0] and out[0, 1, 0] == 0 and out[0, 2].tolist() == [14, 13, 13]
    assert apply_exposure(img, np.diag([1.1, 1.1, 1.1]), np.full(3, 2.0))[0, 0].tolist() == [0, 0, 0]


def test_view_transform_maps_each_frame_to_the_output_exposure(room):
    base, gained = room
    cal = PhotometricCalib(tuple(gained.frame_ids), GAINS_RGB.copy(), np.zeros((8, 3)))
    to_mean = ViewColorTransform(cal, gained.frame_ids)
    for k in (1, 2):
        out = to_mean(k, gained.frames.load(k)[0]).astype(int)
        assert np.abs(out - base.frames.load(k)[0].astype(int)).max() <= 1  # rounding of the two steps
    to_frame2 = ViewColorTransform(cal, gained.frame_ids, exposure_frame=gained.frame_ids[2])
    out = to_frame2(1, gained.frames.load(1)[0]).astype(int)
    want = base.frames.load(1)[0] * GAINS_RGB[2]  # frame 1's view at frame 2's exposure
    assert np.abs(out - want).max() <= 2
    with pytest.raises(ValueError, match="exposure_frame"):
        ViewColorTransform(cal, gained.frame_ids, exposure_frame="nope")


def test_renderer_applies_the_calibration_and_matches_a_frame(room):
    base, gained = room
    cal = PhotometricCalib(tuple(gained.frame_ids), GAINS_RGB.copy(), np.zeros((8, 3)))
    sc = dataclasses.replace(gained, photometric=cal)
    k = 3
    others = sc.subset([j for j in range(8) if j != k])  # keeps the calibration (lookup by id)
    assert others.photometric is cal
    f_base, f_gained = base.frame(k), gained.frame(k)

    def err(cfg, real):
        out = Renderer(others, cfg).render(f_gained.T_world_cam, f_gained.K)
        m = out.valid
        return float(np.abs(out.color[m].astype(float) - real[m].astype(float)).mean())

    off = err(RenderConfig(use_photometric=False), f_gained.color)
    match = err(RenderConfig(exposure_frame=sc.frame_ids[k]), f_gained.color)
    mean = err(RenderConfig(predict_exposure=False), f_base.color)
    assert match < 0.5 * off and mean < 0.5 * off


def test_store_round_trip_and_errors(room, tmp_path):
    _, gained = room
    cal = calibrate_photometric(gained, PhotometricConfig(num_neighbors=2), show_progress=False)
    d = save_scene(gained.subset(range(4)), tmp_path / "s")
    assert load_scene(d).photometric is None
    with pytest.raises(SceneError, match="frame ids"):
        save_photometric(d, cal)  # 8 frames vs the scene's 4
    sub = PhotometricCalib(cal.frame_ids[:4], cal.gain[:4], cal.bias[:4], cal.model, cal.stats)
    before = np.load(d / "color.npy").copy()
    save_photometric(d, sub)
    back = load_scene(d).photometric
    assert back.frame_ids == sub.frame_ids and np.array_equal(back.gain, sub.gain) and np.array_equal(back.bias, sub.bias)
    assert np.array_equal(np.load(d / "color.npy"), before)  # the given images are never touched
    # save_scene carries the calibration along.
    d2 = save_scene(load_scene(d), tmp_path / "s2")
    assert np.array_equal(load_scene(d2).photometric.gain, sub.gain)
    (d / PHOTOMETRIC_FILE).write_text("{not json")
    with pytest.raises(SceneError, match="corrupt JSON"):
        load_scene(d)
    (d / PHOTOMETRIC_FILE).write_text(json.dumps({"format": "other"}))
    with pytest.raises(SceneError, match="unknown format"):
        load_scene(d)


def test_cli_photometric(room, tmp_path, capsys):
    from presim.cli import main

    _, gained = room
    d = save_scene(gained.subset(range(5)), tmp_path / "s")
    assert main(["photometric", str(d)]) == 0
    assert "wrote" in capsys.readouterr().out
    cal = load_scene(d).photometric
    assert np.abs(cal.gain / (GAINS_RGB[:5] / GAINS_RGB[:5].mean(axis=0)) - 1).max() < 0.01
    assert main(["photometric", str(d)]) == 1  # exists: refuses without --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["photometric", str(d), "--overwrite", "--model", "gain"]) == 0
    assert load_scene(d).photometric.model == "gain"
    assert main(["photometric", str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err
    assert "error" in err and "Traceback" not in err


def _known_affine() -> tuple[np.ndarray, np.ndarray]:
    """8 forward colour matrices (white-balance tilt + cross-talk up to 8 %) and biases, mean = identity / 0."""
    rng = np.random.default_rng(3)
    A = np.stack([np.diag(GAINS_RGB[k]) + rng.uniform(-0.08, 0.08, (3, 3)) * (1 - np.eye(3)) for k in range(8)])
    A = A @ np.linalg.inv(A.mean(axis=0))
    b = rng.uniform(-6.0, 6.0, (8, 3))
    return A, b - b.mean(axis=0)


@pytest.mark.slow
def test_known_3x3_colour_transforms_are_recovered_within_1_percent(room):
    base, _ = room
    A, b = _known_affine()
    radiance = base.frames.color.astype(np.float64)  # = 0.75 x the texture (nothing clips)
    obs = np.einsum("kab,khwb->khwa", A, radiance) + b[:, None, None, :]
    sc = dataclasses.replace(base, frames=ArrayFrameSource(np.clip(np.floor(obs + 0.5), 0, 255).astype(np.uint8),
                                                           base.frames.depth_m))
    cal = calibrate_photometric(sc, PhotometricConfig(model="affine"), show_progress=False)
    assert cal.model == "affine" and cal.matrix.shape == (8, 3, 3) and cal.vignetting is None
    np.testing.assert_allclose(cal.matrix.mean(axis=0), np.eye(3), atol=1e-9)  # anchored
    # Within 1 %: the recovered transforms predict every frame's colours of the scene's radiance to
    # 1 % of full scale (2.55 levels), and the matrix entries to 0.015 (cross-talk terms are only as
    # well determined as the texture's colours are spread: the room's palette is small).
    pred = np.einsum("kab,khwb->khwa", cal.matrix, radiance) + cal.bias[:, None, None, :]
    print("max colour error (levels)", np.abs(pred - obs).max(), "max entry error", np.abs(cal.matrix - A).max())
    assert np.abs(pred - obs).max() < 2.55
    assert np.abs(cal.matrix - A).max() < 0.015
    np.testing.assert_allclose(cal.gain, np.diagonal(cal.matrix, axis1=1, axis2=2))
    # Round trip through JSON keeps the model.
    back = PhotometricCalib.from_json(json.loads(json.dumps(cal.to_json())))
    assert back.model == "affine" and np.array_equal(back.matrix, cal.matrix)


@pytest.mark.slow
def test_known_vignetting_is_recovered_within_1_percent(room):
    from presim.capture.calibration import vignetting_radius_sq

    base, _ = room
    K = base.intrinsics[0]
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    r2 = vignetting_radius_sq(np.stack([u.ravel(), v.ravel()], 1), K).reshape(K.height, K.width)
    k1, k2 = 0.35, -0.1  # 25 % fall-off at the corners
    fall = 1.0 / (1.0 + k1 * r2 + k2 * r2 ** 2)
    obs = base.frames.color.astype(np.float64) * fall[None, :, :, None] * GAINS_RGB[:, None, None, :]
    sc = dataclasses.replace(base, frames=ArrayFrameSource(np.clip(np.floor(obs + 0.5), 0, 255).astype(np.uint8),
                                                           base.frames.depth_m))
    cal = calibrate_photometric(sc, PhotometricConfig(model="gain", vignetting=True), show_progress=False)
    rr = np.linspace(0.0, 1.0, 21) ** 2
    got = 1.0 / (1.0 + cal.vignetting[0] * rr + cal.vignetting[1] * rr ** 2)
    want = 1.0 / (1.0 + k1 * rr + k2 * rr ** 2)
    assert np.abs(got / want - 1.0).max() < 0.01, cal.vignetting
    assert np.abs(cal.gain / GAINS_RGB - 1.0).max() < 0.01
    # Without the vignetting term the gains still come out (it is shared by all frames) but the
    # residual is larger.
    plain = calibrate_photometric(sc, PhotometricConfig(model="gain"), show_progress=False)
    assert np.mean(cal.stats["rms_after"]) < np.mean(plain.stats["rms_after"])


def test_renderer_applies_affine_and_vignetting_at_the_source(room):
    """A calibration with known 3x3 transforms and vignetting maps every frame back to the radiance
    (mean exposure, no vignetting); matching a frame puts its transform and vignetting back."""
    from presim.capture.calibration import vignetting_radius_sq
    from presim.photometric.apply import SourceColorCorrection, correct_colors, vignetting_gain_map

    base, _ = room
    A, b = _known_affine()
    K = base.intrinsics[0]
    Wmap = vignetting_gain_map(K, (0.3, 0.0))
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    r2 = vignetting_radius_sq(np.stack([u.ravel(), v.ravel()], 1), K).reshape(K.height, K.width)
    np.testing.assert_allclose(Wmap, 1.0 + 0.3 * r2, rtol=1e-6)
    radiance = base.frames.color.astype(np.float64)
    obs = np.einsum("kab,khwb->khwa", A, radiance / Wmap[None, :, :, None]) + b[:, None, None, :]
    obs8 = np.clip(np.floor(obs + 0.5), 0, 255).astype(np.uint8)
    cal = PhotometricCalib(tuple(base.frame_ids), np.diagonal(A, axis1=1, axis2=2).copy(), b, "affine", {}, A, (0.3, 0.0))
    assert not cal.per_channel
    corr = SourceColorCorrection(cal, base.frame_ids, base.intrinsics)
    back = corr(2, obs8[2]).astype(int)
    assert np.abs(back - base.frames.color[2].astype(int)).max() <= 2  # two roundings, W <= 1.3
    assert np.array_equal(corr(2, obs8[2]), correct_colors(obs8[2], A[2], b[2], np.eye(3), np.zeros(3), Wmap))
    sc = dataclasses.replace(base, frames=ArrayFrameSource(obs8, base.frames.depth_m), photometric=cal)
    k = 3
    others = sc.subset([j for j in range(8) if j != k])
    f = sc.frame(k)

    def err(cfg, real):
        out = Renderer(others, cfg).render(f.T_world_cam, f.K)
        return float(np.abs(out.color[out.valid].astype(float) - real[out.valid].astype(float)).mean())

    off = err(RenderConfig(use_photometric=False), f.color)
    assert err(RenderConfig(exposure_frame=sc.frame_ids[k]), f.color) < 0.5 * off
    assert err(RenderConfig(predict_exposure=False), base.frames.color[k]) < 0.5 * off
