"""The sample scene's one config: size, capture, room options and the depth-sensor corruption."""

from __future__ import annotations

from dataclasses import dataclass

from presim.sensors.noise import QuadraticNoiseConfig

__all__ = ["SampleSceneConfig"]


@dataclass(frozen=True)
class SampleSceneConfig:
    """How the sample scene is built, captured and corrupted. All fields have working defaults."""

    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    num_frames: int = 60
    """Frames along the capture trajectory (its shape does not change; more frames = denser)."""
    hfov_deg: float = 62.0
    """Horizontal field of view (Kinect-like); square pixels, principal point at the image centre."""
    frame_rate_hz: float = 5.0
    """Time stamps are ``frame_idx / frame_rate_hz`` seconds."""
    num_objects: int = 5
    """Objects on the table, 3..5, taken in this order: box, can, bracket (non-convex), ball, rock."""
    door: bool = True
    """A door-sized gap in the north wall leading into a short closed corridor."""
    ceiling: bool = True
    """Close the room with a ceiling (otherwise upward rays see nothing: depth 0, black)."""
    shadows: bool = True
    """Hard shadows of the main light (one shadow ray per lit pixel)."""
    # ---- depth corruption (see corrupt_depth) ----
    noise_sigma0_m: float = 0.0005
    """Depth noise standard deviation at z = 0, metres."""
    noise_k_per_m: float = 0.0015
    """Depth noise grows as ``sigma(z) = noise_sigma0_m + noise_k_per_m * z**2`` (structured-light;
    :class:`presim.sensors.noise.QuadraticNoiseConfig`, see :attr:`depth_noise`)."""
    min_range_m: float = 0.3
    """No depth closer than this (sensor minimum range)."""
    max_range_m: float = 4.0
    """No depth beyond this (sensor maximum range)."""
    dark_albedo: float = 0.05
    """Surfaces with albedo luminance below this return no depth (with ``dark_dropout`` probability)."""
    dark_dropout: float = 0.9
    """Probability that a dark pixel has no depth."""
    grazing_deg: float = 78.0
    """Incidence angle (ray vs. surface normal) around which depth drops out (ramp +-6 degrees)."""
    edge_shadow_px: int = 3
    """Width of the hole on the background left of a nearer surface (projector shadow), pixels."""
    edge_dilate_px: int = 1
    """Foreground depth grows this many pixels over the background at depth edges."""
    shift_px: tuple[int, int] = (2, 1)
    """Color/depth misregistration: depth is shifted by (du, dv) pixels relative to the color."""
    speckle_dropout: float = 0.003
    """Fraction of random isolated missing pixels."""

    @property
    def depth_noise(self) -> QuadraticNoiseConfig:
        """The axial noise law of :func:`~presim.capture.sample_scene.corrupt_depth` (fields above)."""
        return QuadraticNoiseConfig(sigma0_m=self.noise_sigma0_m, k_per_m=self.noise_k_per_m)
