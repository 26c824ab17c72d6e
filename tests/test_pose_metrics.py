"""Pose error functions: answers known on paper, numpy vs torch vs the numba grid, VSD on a
synthetic scene, and AUC against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from presim.pose import curves, metrics, metrics_torch as mt
from presim.pose.nn_grid import NNGrid, NNGridConfig, adi_batch_kdtree

K = np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]])
I3 = np.eye(3)


def _box_points(n_side: int = 6, size=(0.1, 0.06, 0.04)) -> np.ndarray:
    """Points on the surface grid of a box centred at the origin: symmetric under 180 deg about z."""
    g = np.linspace(-0.5, 0.5, n_side)
    pts = np.array([[x, y, z] for x in g for y in g for z in g
                    if max(abs(x), abs(y), abs(z)) == 0.5]) * np.asarray(size)
    return pts


def _random_poses(n, rng, rot_noise=0.2, t_noise=0.03):
    R_g = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    t_g = rng.normal(0, 0.05, (n, 3)) + [0, 0, 0.8]
    dR = Rotation.from_rotvec(rng.normal(0, rot_noise, (n, 3))).as_matrix()
    return R_g @ dR, t_g + rng.normal(0, t_noise, (n, 3)), R_g, t_g


# ---- analytic ----------------------------------------------------------------------------------

def test_identity_pose_gives_zero_errors():
    pts = _box_points()
    R, t = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix(), np.array([0.01, -0.02, 0.7])
    syms = metrics.symmetry_transformations()
    assert metrics.add(R, t, R, t, pts) == 0.0
    assert metrics.adi(R, t, R, t, pts) == 0.0
    assert metrics.proj(R, t, R, t, K, pts) == 0.0
    assert metrics.re(R, R) == pytest.approx(0.0, abs=1e-5)
    assert metrics.te(t, t) == 0.0
    assert metrics.mssd(R, t, R, t, pts, syms) == 0.0
    assert metrics.mspd(R, t, R, t, K, pts, syms) == 0.0


def test_pure_translation_gives_add_equal_to_distance():
    pts = _box_points()
    R, t = Rotation.from_euler("z", 40, degrees=True).as_matrix(), np.array([0.0, 0.0, 0.8])
    d = np.array([0.003, -0.004, 0.012])  # |d| = 13 mm
    assert metrics.add(R, t + d, R, t, pts) == pytest.approx(0.013, rel=1e-12)
    assert metrics.te(t + d, t) == pytest.approx(0.013, rel=1e-12)
    assert metrics.adi(R, t + d, R, t, pts) <= 0.013 + 1e-12
    assert metrics.mssd(R, t + d, R, t, pts, metrics.symmetry_transformations()) == pytest.approx(0.013)


def test_translation_parallel_to_image_shifts_projection_by_fx_dx_over_z():
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])  # all at the same depth
    t = np.array([0.0, 0.0, 1.0])
    assert metrics.proj(I3, t + [0.002, 0, 0], I3, t, K, pts) == pytest.approx(600 * 0.002 / 1.0)
    assert metrics.mspd(I3, t + [0.002, 0, 0], I3, t, K, pts, np.eye(4)[None]) == pytest.approx(1.2)


def test_rotation_error_in_degrees():
    R1 = Rotation.from_rotvec([0, 0, math.radians(30)]).as_matrix()
    R2 = Rotation.from_rotvec([math.radians(45), 0, 0]).as_matrix()
    assert metrics.re(R1, I3) == pytest.approx(30.0)
    assert metrics.re(R2 @ R1, R1) == pytest.approx(45.0)
    assert metrics.re(np.diag([1.0, -1.0, -1.0]), I3) == pytest.approx(180.0)  # 180 deg about x


def test_symmetric_object_rotated_by_its_symmetry():
    pts = _box_points()
    R_sym = Rotation.from_euler("z", 180, degrees=True).as_matrix()  # the box's symmetry
    R_g, t_g = Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix(), np.array([0.02, 0.01, 0.9])
    R_e = R_g @ R_sym
    assert metrics.adi(R_e, t_g, R_g, t_g, pts) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add(R_e, t_g, R_g, t_g, pts) > 0.02
    assert metrics.add_s(R_e, t_g, R_g, t_g, pts, symmetric=True) == pytest.approx(0.0, abs=1e-12)
    syms = metrics.symmetry_transformations([np.block([[R_sym, np.zeros((3, 1))], [np.zeros((1, 3)), 1]])])
    assert len(syms) == 2
    assert metrics.mssd(R_e, t_g, R_g, t_g, pts, syms) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mspd(R_e, t_g, R_g, t_g, K, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert metrics.mssd(R_e, t_g, R_g, t_g, pts, syms[:1]) > 0.02  # identity only


def test_continuous_symmetry_discretisation_as_bop():
    syms = metrics.symmetry_transformations((), [(np.array([0, 0, 1.0]), np.array([0, 0, 0.01]))], 0.01)
    assert len(syms) == math.ceil(math.pi / 0.01) == 315
    np.testing.assert_allclose(syms[0], np.eye(4), atol=1e-12)  # identity included (i = 0)
    for S in syms[::50]:
        assert S[2, 3] == pytest.approx(0.0, abs=1e-12)  # rotation about the axis keeps the offset point
        np.testing.assert_allclose(S[:3, :3] @ [0, 0, 0.01] + S[:3, 3], [0, 0, 0.01], atol=1e-12)
    # A cylinder-like ring rotated by any angle about its axis: MSSD ~ discretisation error.
    ang = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    ring = np.stack([0.05 * np.cos(ang), 0.05 * np.sin(ang), np.zeros_like(ang)], 1)
    R = Rotation.from_euler("z", 0.123, degrees=False).as_matrix()
    t = np.array([0, 0, 0.8])
    assert metrics.mssd(R, t, I3, t, ring, syms) < 0.01 * 0.1  # < step x diameter


# ---- torch and grid against the numpy reference ------------------------------------------------

def test_torch_matches_numpy_reference():
    rng = np.random.default_rng(0)
    pts = _box_points(8)
    R_e, t_e, R_g, t_g = _random_poses(40, rng)
    syms = metrics.symmetry_transformations((), [(np.array([0, 0, 1.0]), np.zeros(3))], 0.05)
    b = mt.as_batch(R_e, t_e, R_g, t_g)
    P = torch.as_tensor(pts)
    got = {
        "add": mt.add(*b, P), "adi": mt.adi(*b, P), "proj": mt.proj(*b, torch.as_tensor(K), P),
        "re": mt.re(b[0], b[2]), "te": mt.te(b[1], b[3]), "mssd": mt.mssd(*b, P, syms),
        "mspd": mt.mspd(*b, torch.as_tensor(K), P, syms),
    }
    for i in range(len(R_e)):
        a = (R_e[i], t_e[i], R_g[i], t_g[i])
        assert got["add"][i].item() == pytest.approx(metrics.add(*a, pts), rel=1e-9)
        assert got["adi"][i].item() == pytest.approx(metrics.adi(*a, pts), rel=1e-9)
        assert got["proj"][i].item() == pytest.approx(metrics.proj(*a, K, pts), rel=1e-9)
        assert got["re"][i].item() == pytest.approx(metrics.re(R_e[i], R_g[i]), abs=1e-6)
        assert got["te"][i].item() == pytest.approx(metrics.te(t_e[i], t_g[i]), rel=1e-12)
        assert got["mssd"][i].item() == pytest.approx(metrics.mssd(*a, pts, syms), rel=1e-9)
        assert got["mspd"][i].item() == pytest.approx(metrics.mspd(*a, K, pts, syms), rel=1e-9)
    # Per-pose camera matrices (E, 3, 3) give the same result as a shared one.
    Kb = torch.as_tensor(np.repeat(K[None], len(R_e), 0))
    torch.testing.assert_close(mt.proj(*b, Kb, P), got["proj"])
    # Chunking does not change results.
    torch.testing.assert_close(mt.adi(*b, P, chunk_elems=len(pts) ** 2 * 3), got["adi"])
    torch.testing.assert_close(mt.mssd(*b, P, syms, chunk_elems=10), got["mssd"])


@pytest.mark.parametrize("far", [False, True])
def test_grid_and_batched_kdtree_adi_match_reference(far):
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 0.03, (700, 3)) * [1.5, 1.0, 0.6]
    R_e, t_e, R_g, t_g = _random_poses(60, rng, rot_noise=1.0 if far else 0.1, t_noise=0.2 if far else 0.01)
    ref = np.array([metrics.adi(R_e[i], t_e[i], R_g[i], t_g[i], pts) for i in range(len(R_e))])
    grid = NNGrid(pts, NNGridConfig(max_cells=20 ** 3, margin_frac=0.2))
    np.testing.assert_allclose(grid.adi(R_e, t_e, R_g, t_g), ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(adi_batch_kdtree(pts, R_e, t_e, R_g, t_g), ref, rtol=1e-12, atol=1e-15)


# ---- VSD on a synthetic plate ------------------------------------------------------------------

def _plate(side=0.1):
    h = side / 2
    pts = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], dtype=np.float64)
    return pts, np.array([[0, 1, 2], [0, 2, 3]])


def test_vsd_on_synthetic_plate():
    pts, faces = _plate()
    render = metrics.MeshDepthRenderer(pts, faces)
    Kp = np.array([[500.0, 0, 159.5], [0, 500.0, 119.5], [0, 0, 1]])
    t_g = np.array([0.0, 0.0, 0.5])
    depth_test = render(I3, t_g, Kp, 320, 240)
    assert (depth_test > 0).sum() == pytest.approx(100 * 100, rel=0.03)  # 0.1 m at 0.5 m, f=500
    assert depth_test[120, 160] == pytest.approx(0.5, abs=1e-6)
    diam = float(np.sqrt(2) * 0.1)
    taus = [0.05, 0.2, 0.3, 0.4, 0.5]
    args = dict(depth_test=depth_test, K=Kp, delta=0.015, taus=taus, normalized_by_diameter=True,
                diameter=diam, renderer=render)
    assert metrics.vsd(I3, t_g, I3, t_g, **args) == [0.0] * len(taus)
    # Shifted sideways by half the plate: union 1.5 plates, intersection 0.5 (zero distance there).
    e = metrics.vsd(I3, t_g + [0.05, 0, 0], I3, t_g, **args)
    assert all(v == pytest.approx(2 / 3, abs=0.02) for v in e)
    # 5 cm closer to the camera: distances ~0.05 m = 0.354 d everywhere in the intersection.
    e = metrics.vsd(I3, t_g - [0, 0, 0.05], I3, t_g, **args)
    assert e[0] > 0.99 and e[1] > 0.99 and e[2] > 0.99    # tau < 0.354 d: every pixel fails
    assert e[4] < 0.25                                       # tau = 0.5 d: only the silhouette growth
    # Nothing visible at all (both behind the camera): error 1, as bop_toolkit.
    assert metrics.vsd(I3, -t_g, I3, -t_g, **args) == [1.0] * len(taus)


# ---- curves ------------------------------------------------------------------------------------

def test_voc_auc_hand_computation():
    # n = 4: rec = [0.02, 0.04], prec = [1/4, 2/4]; mrec = [0, .02, .04, .1], mpre = [0, .25, .5, .5]
    # area = .02*.25 + .02*.5 + .06*.5 = 0.045 -> / 0.1 = 0.45
    assert curves.voc_auc([0.04, np.inf, 0.02, 0.2], 0.1) == pytest.approx(0.45)
    # Ties take the first of their run: rec = [.05, .05] -> steps (0->.05: 1/2), (.05->.1: 1)
    assert curves.voc_auc([0.05, 0.05], 0.1) == pytest.approx((0.05 * 0.5 + 0.05 * 1.0) / 0.1)
    assert curves.voc_auc([np.inf, np.inf], 0.1) == 0.0
    assert curves.voc_auc([0.0], 0.1) == pytest.approx(1.0)
    # Errors as fractions of the diameter, 0-100 %: same definition with max 1.0.
    assert curves.voc_auc([0.4, np.inf, 0.2, 2.0], 1.0) == pytest.approx(0.45)
    with pytest.raises(ValueError, match="NaN"):
        curves.voc_auc([np.nan])


def test_auc_of_uniform_error_distribution():
    # Errors d_i = (i - 1/2)/n x 0.1 m, i = 1..n: the exact CDF area is 1/2. VOCap credits each
    # step with the accuracy at its right end: (1/2n)(1/n) + sum_{i>=2} (1/n)(i/n) + (1/2n)(1)
    # = 1/2 + 1/n - 1/(2n^2) (in units of the 0.1 m range).
    n = 1000
    e = (np.arange(n) + 0.5) / n * 0.1
    assert curves.voc_auc(e, 0.1) == pytest.approx(0.5 + 1 / n - 0.5 / n ** 2, abs=1e-12)
    assert curves.auc_trapezoid(e, 0.1, 1000) == pytest.approx(0.5, abs=2e-3)
    # Half the targets missing: half the area.
    assert curves.voc_auc(np.concatenate([e, np.full(n, np.inf)]), 0.1) == pytest.approx(0.25 + 0.5 / n - 0.25 / n ** 2, abs=1e-12)


def test_accuracy_curve_is_strict():
    e = [0.01, 0.02, 0.03, np.inf]
    np.testing.assert_allclose(curves.accuracy_curve(e, [0.0, 0.02, 0.025, 1.0]), [0, 0.25, 0.5, 0.75])
    assert curves.accuracy_at(e, 0.02) == 0.25


def test_fast_adi_exact_for_identical_non_orthonormal_rotation():
    """LM-O's GT rotations are up to 2e-3 non-orthonormal; GT-as-estimate must still give 0."""
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 0.05, (300, 3))
    R = Rotation.from_euler("xyz", [30, 40, 50], degrees=True).as_matrix() * (1 + 2e-3 * rng.normal(size=(3, 3)))
    t = np.array([0.05, 0.0, 0.9])
    assert metrics.adi(R, t, R, t, pts) == 0.0
    assert NNGrid(pts).adi(R[None], t[None], R[None], t[None])[0] == pytest.approx(0.0, abs=1e-15)
    assert adi_batch_kdtree(pts, R[None], t[None], R[None], t[None])[0] == pytest.approx(0.0, abs=1e-15)
    b = mt.as_batch(R[None], t[None], R[None], t[None])
    assert mt.adi(*b, torch.as_tensor(pts))[0].item() == pytest.approx(0.0, abs=1e-15)
