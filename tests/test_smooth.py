"""The renderer's reconstruction filter (presim.imaging.gaussian, presim.imaging.torch_ops) and its fit on the
capture (presim.evaluation.smooth_fit, presim fit-filter)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from presim.capture.scene import ArrayFrameSource, SceneError
from presim.capture.store import load_scene, save_render_filter, save_scene
from presim.evaluation.eval_views import EvalConfig, eval_views, uses_fitted_filter
from presim.evaluation.smooth_fit import SmoothFitConfig, fit_smoothing, held_out_frames
from presim.geometry import Intrinsics, look_at
from presim.imaging.gaussian import MIN_SIGMA_PX, gaussian_taps, kernel_size, smooth_colors, smooth_colors_ref
from presim.synthesis.config import RenderConfig
from presim.synthesis.renderer import Renderer
from presim.testing.rect_scene import make_scene, room_rects

K = Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)


def test_gaussian_of_a_single_bright_pixel_is_the_outer_product_of_the_taps():
    img = np.zeros((21, 23, 3), np.uint8)
    img[10, 11] = 200
    for sigma in (0.5, 0.8, 1.3):
        t = gaussian_taps(sigma)
        r = len(t) // 2
        assert len(t) == kernel_size(sigma) and abs(t.sum() - 1.0) < 1e-12 and t[r] == t.max()
        want = np.zeros((21, 23))
        want[10 - r:11 + r, 11 - r:12 + r] = 200.0 * np.outer(t, t)
        ref = smooth_colors_ref(img, sigma)
        np.testing.assert_array_equal(ref[..., 1], np.floor(want + 0.5))
        assert np.abs(smooth_colors(img, sigma).astype(int) - ref).max() <= 1


def test_fast_paths_match_the_reference_and_keep_flat_images():
    from presim.imaging.torch_ops import smooth_colors_torch  # torch only here

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    for sigma in (0.3, 0.6, 0.9, 2.0):
        ref = smooth_colors_ref(img, sigma)
        assert np.abs(smooth_colors(img, sigma).astype(int) - ref).max() <= 1
        assert np.abs(smooth_colors_torch(img, sigma, device="cpu").astype(int) - ref).max() <= 1
        assert ref.std() < img.std()
    flat = np.full((9, 7, 3), 77, np.uint8)
    for fn in (smooth_colors_ref, smooth_colors):
        np.testing.assert_array_equal(fn(flat, 1.0), flat)
        np.testing.assert_array_equal(fn(img, MIN_SIGMA_PX / 2), img)  # below the threshold: identity
    with pytest.raises(ValueError, match="uint8"):
        smooth_colors(img.astype(np.float32), 1.0)
    with pytest.raises(ValueError, match="sigma"):
        smooth_colors_ref(img, float("nan"))


def _scene(noise: float = 0.0, seed: int = 0):
    poses = np.stack([look_at((x, -1.2, 1.3), (0.1 * x, 0.6, 0.5)) for x in np.linspace(-0.35, 0.35, 7)])
    scene = make_scene(room_rects(), poses, K)
    colors = np.stack([scene.frames.load(i)[0] for i in range(len(scene))]).astype(np.float64)
    depths = np.stack([scene.frames.load(i)[1] for i in range(len(scene))])
    colors += np.random.default_rng(seed).normal(0.0, noise, colors.shape)
    frames = ArrayFrameSource(np.clip(np.round(colors), 0, 255).astype(np.uint8), depths)
    return dataclasses.replace(scene, frames=frames)


def test_renderer_applies_the_scene_filter_scaled_to_the_output_camera():
    scene = _scene()
    target = look_at((0.05, -1.15, 1.32), (0.0, 0.6, 0.5))
    plain = Renderer(scene, RenderConfig(smooth_sigma_px=0.0)).render(target, K)
    fitted = dataclasses.replace(scene, render_filter_sigma_px=0.8)
    np.testing.assert_array_equal(Renderer(fitted).render(target, K).color, smooth_colors(plain.color, 0.8))
    np.testing.assert_array_equal(Renderer(fitted, RenderConfig(smooth_sigma_px=0.0)).render(target, K).color,
                                  plain.color)  # the config's value wins over the scene's
    K2 = K.scaled(40, 30)  # half the focal length: half the sigma in output pixels
    plain2 = Renderer(scene, RenderConfig(smooth_sigma_px=0.0)).render(target, K2)
    r2 = Renderer(fitted)
    np.testing.assert_array_equal(r2.render(target, K2).color, smooth_colors(plain2.color, 0.4))
    assert r2.last.ms["smooth"] > 0
    assert Renderer(scene).render(target, K).color.tobytes() == plain.color.tobytes()  # no fit: no filter


def test_fit_grows_with_the_capture_noise_and_never_reads_excluded_frames():
    cfg = SmoothFitConfig(sigmas_px=(0.0, 0.4, 0.8, 1.2, 1.6), max_frames=3)
    clean = fit_smoothing(_scene(), cfg)
    noisy = fit_smoothing(_scene(noise=25.0), cfg)
    assert len(clean.frames) == len(noisy.frames) == 3
    assert noisy.sigma_px > clean.sigma_px and noisy.sigma_px >= 0.8, (clean, noisy)
    assert noisy.psnr_db[cfg.sigmas_px.index(noisy.sigma_px)] == max(noisy.psnr_db)
    # excluded frames are neither scored nor used as views: corrupting them changes nothing
    scene = _scene(noise=25.0)
    a = fit_smoothing(scene, cfg, exclude=[2, 5])
    cols = np.stack([scene.frames.load(i)[0] for i in range(len(scene))])
    cols[[2, 5]] = 255
    deps = np.stack([scene.frames.load(i)[1] for i in range(len(scene))])
    b = fit_smoothing(dataclasses.replace(scene, frames=ArrayFrameSource(cols, deps)), cfg, exclude=[2, 5])
    assert a == b and not {scene.frame_ids[2], scene.frame_ids[5]} & set(a.frames)
    assert held_out_frames(10, 3, exclude=[0]) == [1, 5, 9]
    with pytest.raises(ValueError, match="at least 2 frames"):
        fit_smoothing(scene, cfg, exclude=range(6))


def test_scene_folder_keeps_the_filter_and_names_a_bad_file(tmp_path):
    path = save_scene(dataclasses.replace(_scene(), render_filter_sigma_px=0.7), tmp_path / "s")
    assert load_scene(path).render_filter_sigma_px == 0.7
    save_render_filter(path, 1.1, {"frames": ["a"]})
    assert load_scene(path).render_filter_sigma_px == 1.1
    assert load_scene(path).subset([0, 2]).render_filter_sigma_px == 1.1
    with pytest.raises(SceneError, match="sigma"):
        save_render_filter(path, float("nan"))
    for bad, match in (("{", "corrupt"), (json.dumps({"sigma_px": -2}), "sigma_px"),
                       (json.dumps({"sigma_px": "x"}), "sigma_px"), (json.dumps({}), "corrupt")):
        (path / "render_filter.json").write_text(bad)
        with pytest.raises(SceneError, match=f"render_filter.json.*{match}|{match}.*render_filter"):
            load_scene(path)


def test_cli_fit_filter_writes_what_the_renderer_then_uses(tmp_path, capsys):
    from presim.cli import main

    path = save_scene(_scene(noise=25.0), tmp_path / "s")
    assert main(["fit-filter", str(path), "--frames", "2"]) == 0
    out = json.loads((path / "render_filter.json").read_text())
    assert out["sigma_px"] > 0 and len(out["fit"]["frames"]) == 2 and "PSNR" in capsys.readouterr().out
    assert Renderer(load_scene(path)).smooth_sigma_px == out["sigma_px"]
    assert main(["fit-filter", str(path), "--sigma", "0.3"]) == 0
    assert load_scene(path).render_filter_sigma_px == 0.3


def test_eval_views_fits_on_the_capture_and_only_default_methods_use_it():
    assert uses_fitted_filter("default") and uses_fitted_filter("full") and not uses_fitted_filter("thesis")
    scene = dataclasses.replace(_scene(noise=25.0), render_filter_sigma_px=0.0)  # the scene's own is ignored
    res = eval_views(scene, EvalConfig(target_every=3, methods=("default", "default_nosmooth", "thesis"),
                                       refine=dataclasses.replace(EvalConfig().refine, num_refs=2), complete=None,
                                       smooth=SmoothFitConfig(sigmas_px=(0.0, 0.8, 1.6), max_frames=2),
                                       warmup=False))
    m = res.methods
    assert m["default"]["psnr_covered_db"] > m["default_nosmooth"]["psnr_covered_db"] + 0.5, m
    assert m["thesis"]["psnr_db"] < m["default"]["psnr_db"]
