"""Sensor models: seeded depth noise growing with distance, dropouts, odometry drift, camera spec."""

from __future__ import annotations

import numpy as np
import pytest

from presim.geometry import Intrinsics
from presim.sensors.camera import CameraSpec
from presim.sensors.noise import (
    DepthNoiseConfig, QuadraticNoiseConfig, add_quadratic_noise, apply_depth_noise, depth_noise_sigma_m,
    quadratic_noise_sigma_m,
)
from presim.sensors.odometry import OdometryConfig, WheelOdometry


def test_noise_is_seeded():
    d = np.full((60, 80), 2.0, np.float32)
    cfg = DepthNoiseConfig()
    a = apply_depth_noise(d, np.random.default_rng(7), cfg)
    b = apply_depth_noise(d, np.random.default_rng(7), cfg)
    c = apply_depth_noise(d, np.random.default_rng(8), cfg)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_noise_grows_with_distance():
    cfg = DepthNoiseConfig(dropout_prob=0.0, quantize_m=0.0)
    rng = np.random.default_rng(0)
    stds = []
    for z in (1.0, 3.0, 6.0):
        d = np.full((200, 200), z, np.float32)
        out = apply_depth_noise(d, rng, cfg)
        stds.append(float((out - z).std()))
        assert stds[-1] == pytest.approx(float(depth_noise_sigma_m(np.float32(z), cfg)), rel=0.05)
        assert abs(float((out - z).mean())) < 3 * stds[-1] / 200  # unbiased
    assert stds[0] < stds[1] < stds[2]


def test_dropouts_and_range():
    cfg = DepthNoiseConfig(dropout_prob=0.2, min_range_m=0.5, max_range_m=5.0)
    d = np.full((100, 100), 2.0, np.float32)
    d[:10] = 0.3   # too close
    d[10:20] = 7.0  # too far
    d[20:30] = 0.0  # invalid stays invalid
    out = apply_depth_noise(d, np.random.default_rng(1), cfg)
    assert np.all(out[:30] == 0)
    frac = float((out[30:] == 0).mean())
    assert 0.17 < frac < 0.23
    with pytest.raises(ValueError, match="float32"):
        apply_depth_noise(d.astype(np.float64), np.random.default_rng(1), cfg)


def test_quadratic_law_known_answers_and_seeded_draws():
    """The sample scene's law sigma0 + k z^2: 0.5 mm + 1.5 mm/m^2 * (2 m)^2 = 6.5 mm, 0.5 mm at z = 0,
    and the sampled noise has that spread. No masking: depth 0 gets noise too (the caller masks)."""
    cfg = QuadraticNoiseConfig()
    sig = quadratic_noise_sigma_m(np.float32([0.0, 1.0, 2.0]), cfg)
    assert sig.dtype == np.float32
    np.testing.assert_allclose(sig, [0.0005, 0.002, 0.0065], rtol=1e-6)
    d = np.full((200, 200), 2.0, np.float32)
    out = add_quadratic_noise(d, np.random.default_rng(0), cfg)
    assert out.dtype == np.float32 and out.shape == d.shape
    assert float((out - 2.0).std()) == pytest.approx(0.0065, rel=0.05)
    # The draw is N(0, 1) in float64 cast to float32, one per pixel, in pixel order.
    z = np.random.default_rng(0).standard_normal(d.shape).astype(np.float32)
    assert np.array_equal(out, d + z * quadratic_noise_sigma_m(d, cfg))
    assert np.array_equal(out, add_quadratic_noise(d, np.random.default_rng(0), cfg))
    assert float(np.abs(add_quadratic_noise(np.zeros((50, 50), np.float32), np.random.default_rng(1), cfg)).max()) > 0


def test_odometry_exact_without_drift_and_seeded_drift():
    odo = WheelOdometry(OdometryConfig(drift=False))
    odo.reset(np.random.default_rng(0))
    for _ in range(10):
        T = odo.update(np.array([0.5, 0.0, 0.0]), 0.2)
    assert np.allclose(T[:3, 3], [1.0, 0.0, 0.0])

    def run(seed):
        o = WheelOdometry(OdometryConfig(drift=True))
        o.reset(np.random.default_rng(seed))
        for _ in range(100):
            T = o.update(np.array([0.5, 0.0, 0.1]), 0.1)
        return T

    a, b, c = run(3), run(3), run(4)
    assert np.array_equal(a, b) and not np.allclose(a, c)
    exact = WheelOdometry(OdometryConfig(drift=False))
    for _ in range(100):
        E = exact.update(np.array([0.5, 0.0, 0.1]), 0.1)
    err = np.linalg.norm(a[:3, 3] - E[:3, 3])
    assert 1e-4 < err < 0.5  # drifts, but by a plausible amount over 5 m


def test_camera_spec_intrinsics():
    cap = Intrinsics(615.0, 615.0, 298.4, 247.5, 640, 480)
    spec = CameraSpec(width=320, height=240)
    K = spec.intrinsics(cap)
    assert K.width == 320 and K.fx == pytest.approx(307.5)  # the capture's FOV, resampled
    K2 = CameraSpec(width=320, height=240, hfov_deg=90.0).intrinsics(cap)
    assert K2.fx == pytest.approx(160.0)
    with pytest.raises(ValueError, match="rate_hz"):
        CameraSpec(rate_hz=0)
