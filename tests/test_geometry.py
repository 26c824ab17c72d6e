"""presim.geometry: property tests (round trips) and hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from presim.geometry import (
    T_CV_FROM_GL, Intrinsics, R_to_quat_xyzw, check_rigid, compose, invert, look_at, make_pose, pixel_grid,
    pose_from_tum, pose_to_tum, project, quat_xyzw_to_R, rotation_angle_rad, rotation_z, transform_points,
    unproject, unproject_depth,
)

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
quats = arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(lambda q: np.linalg.norm(q) > 0.1)
vec3 = arrays(np.float64, 3, elements=finite)


def _pose(q, t):
    return make_pose(quat_xyzw_to_R(q), t)


K = Intrinsics(500.0, 510.0, 319.5, 239.5, 640, 480)


# ---- properties -------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(quats, vec3)
def test_T_times_inverse_is_identity(q, t):
    T = _pose(q, t)
    np.testing.assert_allclose(compose(T, invert(T)), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(compose(invert(T), T), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(invert(invert(T)), T, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(quats)
def test_quaternion_round_trip(q):
    R = quat_xyzw_to_R(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    q2 = R_to_quat_xyzw(R)
    qn = q / np.linalg.norm(q)
    # q and -q are the same rotation; R_to_quat returns w >= 0
    assert min(np.abs(q2 - qn).max(), np.abs(q2 + qn).max()) < 1e-9
    assert q2[3] >= 0
    np.testing.assert_allclose(quat_xyzw_to_R(q2), R, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.floats(-0.5, 639.5), st.floats(-0.5, 479.5), st.floats(0.05, 100.0))
def test_project_unproject_round_trip(u, v, z):
    p = unproject(K, np.array([u, v]), np.array(z))
    uv, depth = project(K, p)
    np.testing.assert_allclose(uv, [u, v], atol=1e-8)
    assert depth == pytest.approx(z)


@settings(max_examples=100, deadline=None)
@given(quats, vec3, arrays(np.float64, (5, 3), elements=finite))
def test_transform_points_matches_matrix_and_inverse(q, t, p):
    T = _pose(q, t)
    pa = transform_points(T, p)
    np.testing.assert_allclose(pa, (T @ np.c_[p, np.ones(5)].T).T[:, :3], atol=1e-9)
    np.testing.assert_allclose(transform_points(invert(T), pa), p, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(quats, vec3)
def test_tum_round_trip(q, t):
    T = _pose(q, t)
    np.testing.assert_allclose(pose_from_tum(pose_to_tum(T)), T, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(quats, vec3, quats, vec3, quats, vec3)
def test_compose_associative(q1, t1, q2, t2, q3, t3):
    A, B, C = _pose(q1, t1), _pose(q2, t2), _pose(q3, t3)
    np.testing.assert_allclose(compose(compose(A, B), C), compose(A, compose(B, C)), atol=1e-8)


# ---- hand-computed values ---------------------------------------------------------------------
def test_project_hand_values():
    # x = 0.2, y = -0.1, z = 2: u = 500 * 0.1 + 319.5 = 369.5, v = 510 * -0.05 + 239.5 = 214
    uv, z = project(K, np.array([0.2, -0.1, 2.0]))
    np.testing.assert_allclose(uv, [369.5, 214.0])
    assert z == 2.0
    uv, _ = project(K, np.array([[0.0, 0.0, -1.0]]))
    assert np.isnan(uv).all()  # behind the camera


def test_pixel_centre_convention():
    # the principal point of a centred 640x480 camera is between pixels 319 and 320: (319.5, 239.5)
    Kc = Intrinsics.from_fov(640, 480, 90.0)
    assert (Kc.cx, Kc.cy) == (319.5, 239.5)
    assert Kc.fx == pytest.approx(320.0)  # tan(45 deg) = 1 -> f = W / 2
    assert Kc.hfov_deg == pytest.approx(90.0)
    # halving the resolution: pixel-centre aware principal point
    half = Kc.scaled(320, 240)
    assert (half.cx, half.cy) == (159.5, 119.5) and half.fx == pytest.approx(160.0)
    g = pixel_grid(3, 2)
    assert g.shape == (2, 3, 2) and tuple(g[1, 2]) == (2.0, 1.0)


def test_hand_pose_values():
    # camera 1 m along world x, rotated 90 deg about z: its x axis is world y
    T_world_cam = make_pose(rotation_z(np.pi / 2), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(transform_points(T_world_cam, np.array([1.0, 0.0, 0.0])), [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(invert(T_world_cam)[:3, 3], [0.0, 1.0, 0.0], atol=1e-12)
    # quaternion of 90 deg about z: (0, 0, sin 45, cos 45)
    np.testing.assert_allclose(R_to_quat_xyzw(rotation_z(np.pi / 2)), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    assert rotation_angle_rad(rotation_z(0.3)) == pytest.approx(0.3)
    assert rotation_angle_rad(rotation_z(0.3), rotation_z(0.5)) == pytest.approx(0.2)


def test_look_at_and_gl_conversion():
    T = look_at(np.array([0.0, -2.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)   # optical axis towards the target
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # image down = world down
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)
    # the same camera as an OpenGL pose looks along its -z and has y up
    T_gl = compose(T, invert(T_CV_FROM_GL))
    np.testing.assert_allclose(-T_gl[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(T_gl[:3, 1], [0, 0, 1], atol=1e-12)


def test_unproject_depth_hand_values():
    Ks = Intrinsics(2.0, 2.0, 0.5, 0.5, 2, 2)
    d = np.array([[1.0, 0.0], [2.0, 4.0]], np.float32)
    pts, mask = unproject_depth(Ks, d)
    np.testing.assert_array_equal(mask, [[True, False], [True, True]])
    # (u, v) = (0, 0), z = 1 -> x = (0 - 0.5) / 2 = -0.25; (0, 1) z = 2 -> (-0.5, 0.5, 2); (1, 1) z = 4 -> (1, 1, 4)
    np.testing.assert_allclose(pts, [[-0.25, -0.25, 1.0], [-0.5, 0.5, 2.0], [1.0, 1.0, 4.0]])
    T = make_pose(np.eye(3), [0, 0, 1.0])
    pw, _ = unproject_depth(Ks, d, T)
    np.testing.assert_allclose(pw[:, 2], [2.0, 3.0, 5.0])
    with pytest.raises(ValueError, match="depth shape"):
        unproject_depth(Ks, np.zeros((3, 3), np.float32))


def test_check_rigid_errors():
    with pytest.raises(ValueError, match="my pose: contains non-finite"):
        check_rigid(np.full((4, 4), np.nan), "my pose")
    with pytest.raises(ValueError, match="expected a 4x4"):
        check_rigid(np.eye(3))
    S = np.eye(4)
    S[:3, :3] *= 1.01
    with pytest.raises(ValueError, match="not orthonormal"):
        check_rigid(S)
    M = np.diag([1.0, 1.0, -1.0, 1.0])  # reflection
    with pytest.raises(ValueError, match="not orthonormal"):
        check_rigid(M)
    bad_row = np.eye(4)
    bad_row[3, 0] = 0.5
    with pytest.raises(ValueError, match="last row"):
        check_rigid(bad_row)
    # slightly non-orthonormal input is re-orthonormalised
    R = rotation_z(0.4) + 1e-5
    out = check_rigid(make_pose(R, [1, 2, 3]))
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)


def test_intrinsics_validation():
    with pytest.raises(ValueError, match="focal"):
        Intrinsics(0.0, 1.0, 0.0, 0.0, 10, 10)
    with pytest.raises(ValueError, match="finite"):
        Intrinsics(np.nan, 1.0, 0.0, 0.0, 10, 10)
    with pytest.raises(ValueError, match="3x3"):
        Intrinsics.from_K(np.eye(4), 10, 10)
    assert Intrinsics.from_dict(K.to_dict()) == K


def test_invert_of_one_pose_equals_the_batched_inverse_bit_for_bit():
    """invert's one-pose path (Python floats) gives the same numbers as its batched einsum path."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(2000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    T = make_pose(quat_xyzw_to_R(q), rng.normal(size=(2000, 3)) * 10.0 ** rng.uniform(-3, 2, (2000, 1)))
    batched = invert(T)
    for k in range(len(T)):
        one = invert(T[k])
        assert one.shape == (4, 4) and one.dtype == np.float64
        np.testing.assert_array_equal(one, batched[k])
    np.testing.assert_allclose(compose(T[0], invert(T[0])), np.eye(4), atol=1e-12)
