"""Wheel odometry: integrates the applied base twist, optionally with seeded drift.

Drift model (per step, independent Gaussian): the integrated linear velocity is scaled by
``1 + N(0, trans_noise_frac)`` and the yaw rate by ``1 + N(0, rot_noise_frac)`` plus a constant
``yaw_bias_rad_s`` -- the usual slip/calibration errors, so the error grows with distance travelled.
With drift off the odometry equals the true motion since reset (``T_odom_base`` = start-relative
ground truth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.geometry import make_pose, rotation_z

__all__ = ["OdometryConfig", "integrate_planar", "WheelOdometry"]


@dataclass(frozen=True)
class OdometryConfig:
    """Odometry drift parameters."""

    drift: bool = False
    """Enable the drift model; False = exact odometry."""
    trans_noise_frac: float = 0.02
    """Std of the relative error of the integrated linear velocity (2 % of distance)."""
    rot_noise_frac: float = 0.05
    """Std of the relative error of the integrated yaw rate."""
    yaw_bias_rad_s: float = 0.002
    """Constant yaw-rate bias, rad/s."""


def integrate_planar(x: float, y: float, yaw: float, vx: float, vy: float, wz: float, dt: float) -> tuple[float, float, float]:
    """Exact integration of a constant body twist (vx, vy in m/s, wz in rad/s) over ``dt`` seconds
    (the base moves on a circular arc). Returns the new (x, y, yaw)."""
    if abs(wz) < 1e-9:
        c, s = np.cos(yaw), np.sin(yaw)
        return x + (c * vx - s * vy) * dt, y + (s * vx + c * vy) * dt, yaw
    yaw1 = yaw + wz * dt
    # Integral of R(yaw(t)) [vx, vy] dt for yaw(t) = yaw + wz t.
    ds, dc = np.sin(yaw1) - np.sin(yaw), np.cos(yaw1) - np.cos(yaw)
    dx = (vx * ds + vy * dc) / wz
    dy = (-vx * dc + vy * ds) / wz
    return x + dx, y + dy, yaw1


class WheelOdometry:
    """Integrates applied twists into ``T_odom_base`` (odom = the base pose at reset)."""

    def __init__(self, config: OdometryConfig = OdometryConfig()):
        self.config = config
        self.reset(np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.x = self.y = self.yaw = 0.0

    def update(self, twist_xyw: np.ndarray, dt: float) -> np.ndarray:
        """Integrate the applied (vx, vy, wz) for ``dt``; return the 4x4 ``T_odom_base``."""
        vx, vy, wz = (float(v) for v in twist_xyw)
        if self.config.drift:
            e_t, e_r = self.rng.standard_normal(2)
            s = 1.0 + self.config.trans_noise_frac * e_t
            vx, vy = vx * s, vy * s
            wz = wz * (1.0 + self.config.rot_noise_frac * e_r) + self.config.yaw_bias_rad_s
        self.x, self.y, self.yaw = integrate_planar(self.x, self.y, self.yaw, vx, vy, wz, dt)
        return self.pose()

    def pose(self) -> np.ndarray:
        return make_pose(rotation_z(self.yaw), [self.x, self.y, 0.0])
