"""Sensors of the simulator: RGB-D camera spec, seeded noise models, odometry."""

from presim.sensors.camera import CameraSpec
from presim.sensors.noise import DepthNoiseConfig, QuadraticNoiseConfig, add_quadratic_noise, apply_depth_noise
from presim.sensors.odometry import OdometryConfig, WheelOdometry

__all__ = ["CameraSpec", "DepthNoiseConfig", "apply_depth_noise", "QuadraticNoiseConfig", "add_quadratic_noise",
           "OdometryConfig", "WheelOdometry"]
