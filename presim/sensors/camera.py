"""RGB-D camera sensor spec: where it is mounted, its intrinsics, resolution, rate and noise model."""

from __future__ import annotations

from dataclasses import dataclass

from presim.geometry import Intrinsics
from presim.sensors.noise import DepthNoiseConfig

__all__ = ["CameraSpec"]


@dataclass(frozen=True)
class CameraSpec:
    """An RGB-D camera rendered by the view synthesis engine.

    Example:
        >>> spec = CameraSpec(width=320, height=240, hfov_deg=60.0, rate_hz=10.0)
        >>> spec.intrinsics(None).fx  # doctest: +ELLIPSIS
        277.1...
    """

    name: str = "head_camera"
    """Sensor name (``CameraObservation.sensor_name``)."""
    link: str | None = None
    """URDF link it is mounted on (an OpenCV optical frame); None = the robot's ``camera_link``."""
    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    hfov_deg: float | None = None
    """Horizontal field of view (square pixels, centred principal point). None = the scene's capture
    intrinsics resampled to ``width`` x ``height`` (same field of view as the captured images)."""
    rate_hz: float = 10.0
    """Readings per second of sim time; at most one per step (a rate above 1/dt renders every step)."""
    noise: DepthNoiseConfig | None = None
    """Seeded depth noise model; None = exact synthesized depth."""

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera '{self.name}': image size must be positive, got {self.width}x{self.height}")
        if not self.rate_hz > 0:
            raise ValueError(f"camera '{self.name}': rate_hz must be > 0, got {self.rate_hz}")
        if self.hfov_deg is not None and not 1.0 < self.hfov_deg < 179.0:
            raise ValueError(f"camera '{self.name}': hfov_deg must be in (1, 179), got {self.hfov_deg}")

    def intrinsics(self, capture_K: Intrinsics | None) -> Intrinsics:
        """Intrinsics of the rendered images (``capture_K`` = a captured frame's intrinsics)."""
        if self.hfov_deg is not None or capture_K is None:
            return Intrinsics.from_fov(self.width, self.height, self.hfov_deg or 60.0)
        return capture_K.scaled(self.width, self.height)
