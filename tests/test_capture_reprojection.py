"""reprojection_mae / forward_warp on scenes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from presim.capture.reprojection import forward_warp, reprojection_mae
from presim.capture.scene import ArrayFrameSource, Scene, SceneMeta
from presim.geometry import Intrinsics, make_pose

K = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)


def _plane_scene(shift_x_m: float, Z: float = 2.0) -> Scene:
    """Two frames of a textured fronto-parallel plane at Z; camera 1 moved by shift_x_m along x, its
    image is the first shifted by fx * shift / Z pixels."""
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 256, (24, 64, 3), dtype=np.uint8)
    px = int(round(K.fx * shift_x_m / Z))
    color = np.stack([tex[:, 16:48], tex[:, 16 + px:48 + px]])
    depth = np.full((2, 24, 32), Z, np.float32)
    poses = np.stack([np.eye(4), make_pose(np.eye(3), [shift_x_m, 0, 0])])
    return Scene(["a", "b"], np.array([0.0, 1.0]), poses, [K, K], ArrayFrameSource(color, depth), SceneMeta("t", "t"))


def test_identity_warp_returns_input():
    rng = np.random.default_rng(1)
    c = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    d = rng.uniform(1, 3, (24, 32)).astype(np.float32)
    wc, wd = forward_warp(c, d, K, K, np.eye(4))
    np.testing.assert_array_equal(wc, c)
    np.testing.assert_allclose(wd, d, rtol=1e-6)


def test_plane_shift_zero_error_with_poses():
    s = _plane_scene(0.2)  # 4 px shift
    mae, cov = reprojection_mae(s, 1, 0)
    assert mae == 0.0 and cov == pytest.approx(28 / 32)  # 4 columns uncovered
    base, cov0 = reprojection_mae(s, 1, 0, use_poses=False)
    assert base > 50 and cov0 == 1.0


def test_z_buffer_keeps_nearest():
    c = np.zeros((24, 32, 3), np.uint8)
    c[:, :16] = 200
    d = np.full((24, 32), 4.0, np.float32)
    d[:, :16] = 1.0  # near left half (bright), far right half (dark)
    # move the camera left by 0.2 m: near half shifts 8 px right, far half 2 px: they overlap
    wc, wd = forward_warp(c, d, K, K, make_pose(np.eye(3), [0.2, 0, 0]))
    assert np.all(wc[:, 18:24] == 200) and np.all(wd[:, 18:24] == 1.0)


def test_bad_index():
    with pytest.raises(ValueError, match="target_idx=5 out of range"):
        reprojection_mae(_plane_scene(0.1), 5, 0)
