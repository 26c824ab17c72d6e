"""Telea inpainting in numba (presim/imaging/inpaint.py) against its reference, cv2.inpaint.

The numba kernel reproduces OpenCV's discretisation (queue order with first-in-first-out ties, the
outside arrival times, the border rules, float32 arithmetic), so the two must agree pixel for pixel.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from presim.imaging.inpaint import telea_inpaint
from presim.synthesis.fill import fill_holes


def _cv(color, holes, radius=3):
    return cv2.inpaint(color, holes.astype(np.uint8), radius, cv2.INPAINT_TELEA)


def test_equals_opencv_on_random_masks_every_size_and_radius():
    rng = np.random.default_rng(0)
    n = 0
    for H in (2, 3, 7, 16, 33):
        for W in (2, 5, 12, 31):
            for frac in (0.0, 0.05, 0.4, 0.9, 1.0):
                for radius in (1, 3, 5):
                    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
                    holes = rng.random((H, W)) < frac
                    got = telea_inpaint(img, holes, radius)
                    assert np.array_equal(got, _cv(img, holes, radius)), (H, W, frac, radius)
                    assert np.array_equal(got[~holes], img[~holes])
                    n += 1
    assert n == 300


def test_equals_opencv_on_smooth_images_with_blobs_and_border_holes():
    rng = np.random.default_rng(1)
    for trial in range(12):
        H, W = rng.integers(24, 90, 2)
        img = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (7, 7), 3)
        holes = cv2.dilate((rng.random((H, W)) < 0.01).astype(np.uint8), np.ones((3, 5), np.uint8)) > 0
        holes[0, ::3] = True  # every border row and column
        holes[-1, 1::4] = True
        holes[::5, 0] = True
        holes[2::3, -1] = True
        assert np.array_equal(telea_inpaint(img, holes, 3), _cv(img, holes, 3)), trial


def test_equals_opencv_on_a_real_capture_frame(shared_data):
    # A real colour image with the capture's own missing-depth pixels as holes (thin cracks, object
    # borders and large regions): the case the final fill meets.
    from presim.capture.importers import kinfu

    scene = kinfu.read(shared_data("apc_cardboard_bin_kinfu50"))
    color, depth = scene.frames.load(0)
    holes = ~(depth > 0)
    assert 0.05 < holes.mean() < 0.95
    assert np.array_equal(telea_inpaint(color, holes), _cv(color, holes))
    # Only the small holes, as after view synthesis.
    n, lab, stats, _ = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=4)
    small = holes & (stats[lab, cv2.CC_STAT_AREA] <= 50)
    assert small.any()
    assert np.array_equal(telea_inpaint(color, small), _cv(color, small))


def test_one_row_or_column_images_go_to_opencv_and_no_holes_is_a_copy():
    # OpenCV's border rules read outside a one-row image (two calls can differ), so only what
    # does not depend on that is checked: the known pixels and the shape.
    rng = np.random.default_rng(2)
    for shape in ((1, 9), (8, 1), (1, 1)):
        img = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        holes = rng.random(shape) < 0.5
        out = telea_inpaint(img, holes)
        assert out.shape == img.shape and np.array_equal(out[~holes], img[~holes])
    img = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    out = telea_inpaint(img, np.zeros((6, 7), bool))
    assert np.array_equal(out, img) and out is not img


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="uint8"):
        telea_inpaint(np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), bool))
    with pytest.raises(ValueError, match="do not match"):
        telea_inpaint(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5), bool))


def test_fill_holes_telea_colour_equals_opencv():
    rng = np.random.default_rng(3)
    color = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (5, 5), 2)
    depth = rng.uniform(1, 2, (48, 64)).astype(np.float32)
    valid = rng.random((48, 64)) > 0.01
    c_nb, _ = fill_holes(color, depth, valid, "telea")
    assert np.array_equal(c_nb, _cv(color, ~valid)) and not np.array_equal(c_nb, color)
