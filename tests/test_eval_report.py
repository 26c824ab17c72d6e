"""Pictures of an evaluation (``presim eval-views --save-images``): the strip's panels and the report's order."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from presim.evaluation.report import (
    ERR_MAX, HOLE_RGB, WORST_N, eval_strip, ranking_method, strip_layout, strip_name, write_report,
)


def _inferno(level: int) -> np.ndarray:
    return cv2.applyColorMap(np.array([[level]], np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]


def test_strip_has_four_panels_of_the_target_size():
    H, W = 48, 64
    rng = np.random.default_rng(0)
    real = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    rendered = real.copy()
    rendered[:, W // 2:] = np.clip(real[:, W // 2:].astype(int) + 100, 0, 255)  # right half: error >= 64 levels
    rendered[:, W // 2:] = np.where(real[:, W // 2:] > 155, 0, rendered[:, W // 2:])
    valid = np.ones((H, W), bool)
    valid[:5, :] = False  # a band of holes at the top
    strip = eval_strip(real, rendered, valid, caption="frame-000001 default")
    top, bottom = strip_layout(H, W)
    assert strip.shape == (top + H + bottom, 4 * W, 3) and strip.dtype == np.uint8
    panel = [strip[top:top + H, i * W:(i + 1) * W] for i in range(4)]
    assert np.array_equal(panel[0], real) and np.array_equal(panel[1], rendered)
    # Heat map: no error = the colour map's 0, every error >= ERR_MAX levels = its 255.
    assert (panel[2][:, :W // 2] == _inferno(0)).all()
    assert (panel[2][:, W // 2:] == _inferno(255)).all()
    # Holes panel: magenta exactly at the holes, dimmed grey elsewhere.
    is_hole = (panel[3] == HOLE_RGB).all(axis=2)
    assert np.array_equal(is_hole, ~valid)
    rest = panel[3][valid]
    assert (rest[:, 0] == rest[:, 1]).all() and (rest[:, 1] == rest[:, 2]).all() and rest.max() <= 0.3 * 255 + 1
    # The colour bar under the heat map runs from the map's 0 to its 255.
    lut = np.stack([_inferno(v) for v in range(256)]).astype(int)
    bar = strip[top + H + top // 4 + 1, 2 * W + W // 4:3 * W - W // 4].astype(int)
    dist = np.abs(bar[:, None, :] - lut[None]).max(axis=2)  # (pixel, level)
    assert (dist.min(axis=1) <= 2).all()  # every pixel is a colour of the map
    levels = dist.argmin(axis=1)
    assert (np.diff(levels) >= 0).all() and levels[-1] - levels[0] > 100  # rising from low to high
    # Scaled panels keep the aspect ratio and the hole colour (nearest, not blended).
    small = eval_strip(real, rendered, valid, panel_width=32)
    t2, b2 = strip_layout(24, 32)
    assert small.shape == (t2 + 24 + b2, 128, 3)
    assert (small[t2:t2 + 2, 96:128] == HOLE_RGB).all()
    with pytest.raises(ValueError, match="must be"):
        eval_strip(real, rendered[:10], valid)


def test_strip_greys_pixels_without_real_data():
    real = np.full((20, 30, 3), 100, np.uint8)
    rendered = real.copy()
    rv = np.ones((20, 30), bool)
    rv[:, :4] = False
    strip = eval_strip(real, rendered, np.ones((20, 30), bool), real_valid=rv)
    top, _ = strip_layout(20, 30)
    heat = strip[top:top + 20, 60:90]
    assert (heat[:, :4] == 128).all() and (heat[:, 4:] == _inferno(0)).all()


def _metrics(psnr: float) -> dict[str, float]:
    return {"psnr_db": psnr, "psnr_covered_db": psnr + 1, "psnr_hole_db": float("nan"), "ssim": 0.9, "hole_frac": 0.01}


def test_report_lists_the_worst_five_first_then_the_rest_in_capture_order(tmp_path):
    ids = [f"frame-{i:06d}" for i in range(8)]
    default_psnr = [25.0, 21.0, 27.0, 22.0, 20.0, 26.0, 23.0, 24.0]
    per = {"fixed_1": [_metrics(30.0 - p) for p in default_psnr],  # opposite order: must not rank
           "default": [_metrics(p) for p in default_psnr]}
    out = write_report(tmp_path / "report.md", "| method |\n|---|", ids, per, protocol="Scene `x`: 8 targets")
    text = out.read_text()
    order = re.findall(r"^### (frame-\d+)", text, flags=re.M)
    worst = [ids[i] for i in np.argsort(default_psnr)[:WORST_N]]
    assert order[:WORST_N] == worst == ["frame-000004", "frame-000001", "frame-000003", "frame-000006",
                                        "frame-000007"]
    assert order[WORST_N:] == ["frame-000000", "frame-000002", "frame-000005"]
    assert text.index("## The 5 worst targets (by `default` PSNR)") < text.index(f"### {worst[0]}")
    assert text.index("## Other targets") > text.index(f"### {worst[-1]}")
    # Each target shows the strip of every method, and its table says n/a where it has no holes.
    for tid in ids:
        for m in per:
            assert f"]({strip_name(tid, m)})" in text
    assert "| default | 20.00 | 21.00 | n/a | 0.9000 | 1.00 |" in text
    assert "Scene `x`: 8 targets" in text and "| method |" in text and f"0 to {ERR_MAX:g} grey levels" in text


def test_ranking_method_and_names():
    assert ranking_method(["full", "default"]) == "default"
    assert ranking_method(["DIBR", "full"]) == "DIBR"
    assert strip_name("rgb/1305031102.175304", "default") == "rgb_1305031102.175304_default.png"
