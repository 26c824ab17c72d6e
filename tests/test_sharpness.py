"""Sharpness scores and sharpness-aware views (presim/capture/sharpness.py) in the renderer."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from presim.capture.scene import ArrayFrameSource
from presim.capture.sharpness import ViewSharpness, sharpness_score
from presim.geometry import Intrinsics
from presim.synthesis.renderer import RenderConfig, Renderer
from presim.testing import rect_scene as S


@pytest.fixture(scope="module")
def room():
    K = Intrinsics.from_fov(160, 120, 60.0)
    return S.make_scene(S.room_rects(), S.orbit_poses(6, span_m=0.5), K)


def test_blurred_frame_ranks_last(room):
    cols = room.frames.color.copy()
    cols[3] = cv2.GaussianBlur(cols[3], (0, 0), 1.5)
    scores = [sharpness_score(c) for c in cols]
    assert int(np.argmin(scores)) == 3
    assert all(0.0 <= s <= 1.0 for s in scores)


def test_one_directional_motion_blur_ranks_last(room):
    cols = room.frames.color.copy()
    k = np.zeros((1, 7), np.float32)
    k[0] = 1 / 7  # horizontal motion blur, 7 px
    cols[1] = cv2.filter2D(cols[1], -1, k)
    assert int(np.argmin([sharpness_score(c) for c in cols])) == 1


def test_score_ignores_exposure_and_checks_size(room):
    c = room.frames.color[2]
    dark = (c.astype(np.float32) * 0.5).round().astype(np.uint8)
    assert abs(sharpness_score(dark) - sharpness_score(c)) < 0.03
    with pytest.raises(ValueError, match="larger"):
        sharpness_score(np.zeros((5, 5, 3), np.uint8))


def test_blurred_candidates_are_demoted_and_down_weighted(room):
    cols = room.frames.color.copy()
    cols[2] = cv2.GaussianBlur(cols[2], (0, 0), 2.0)
    vs = ViewSharpness(lambda v: cols[v])
    perm = vs.order(np.array([2, 1, 3]))
    assert [int(x) for x in np.array([2, 1, 3])[perm]] == [1, 3, 2]
    assert vs.quality(2) < 0.8 * vs.quality(1) and max(vs.quality(1), vs.quality(3)) == 1.0
    # The renderer warps the blurred nearest view last.
    sc = dataclasses.replace(room, frames=ArrayFrameSource(cols, room.frames.depth_m))
    T = room.T_world_cam[2].copy()
    others = sc  # the blurred frame 2 sits exactly at the target: nearest candidate
    plain = Renderer(others, RenderConfig(fixed_views=2))
    plain.render(T, room.intrinsics[0])
    assert plain.last.views[0] == 2
    sharp = Renderer(others, RenderConfig(fixed_views=2, sharpness=True, blend=True))
    out = sharp.render(T, room.intrinsics[0])
    assert 2 not in sharp.last.views[:1] and out.valid.mean() > 0.9
