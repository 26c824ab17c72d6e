"""Fusion of aligned captured depth with estimated depth (thesis §5.3.4.2, eq. 5.6-5.7).

The aligned sensor depth ``a`` (:func:`presim.depth.align.align_depth`) is metric and reliable where
the sensor works, but has holes (the stereo dead band, reflective, dark and grazing surfaces) and
residual edge errors; the estimated depth ``e`` (the refined depth, scaled by the alignment's scale)
follows the colour edges and covers those holes but is a propagated guess away from measurements.
The thesis picks, per pixel, the depth that maximises reliability x probability of both sources
(eq. 5.6), with the sensor's reliability falling with distance inside its range (eq. 5.7). Its
estimate reliability (eq. 5.8) compares COLMAP's photometric and geometric stages, which we do not
have. Our rule, a decision list over the two candidates ``{a, e}``:

1. both valid and agreeing (``|a - e| <= agree_rel * e``): **a** (the sensor's metric value; a
   constant offset within the tolerance is kept, never averaged away); with
   ``agree_value="estimate"``: **e** (the refined depth's colour-guided median has removed part of
   the sensor noise there);
2. both valid, disagreeing, within ``edge_band_px`` of a depth discontinuity of ``e``: **e** (edges
   follow the colour image; the alignment leaves a residual band at occlusion boundaries);
3. both valid, disagreeing, away from edges: **a** when the sensor reliability ``r_c`` (eq. 5.7 with
   ``min_range_m`` / ``max_range_m``) is at least ``min_sensor_reliability``, else **e**;
4. only ``a`` valid: **a** if ``r_c > 0`` (inside the sensor's range), else 0;
5. only ``e`` valid: **e** (fills the dead band, reflective and dark regions);
6. neither: 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["FuseConfig", "FusedDepth", "fuse_depth", "sensor_reliability", "SOURCE_SENSOR", "SOURCE_ESTIMATE"]

SOURCE_NONE, SOURCE_SENSOR, SOURCE_ESTIMATE = 0, 1, 2


@dataclass(frozen=True)
class FuseConfig:
    """Parameters of :func:`fuse_depth`."""

    agree_rel: float = 0.03
    """Sensor and estimate agree when they differ by at most this fraction of the estimate."""
    edge_rel: float = 0.05
    """A 4-neighbour depth step larger than this fraction is a discontinuity of the estimate."""
    edge_band_px: int = 2
    """Disagreements within this many pixels of a discontinuity take the estimate (rule 2)."""
    min_range_m: float = 0.2
    """MinD of eq. 5.7: nearest depth the sensor measures (Kinect/RealSense class: ~0.2-0.5 m)."""
    max_range_m: float = 8.0
    """MaxD of eq. 5.7: farthest depth the sensor measures."""
    min_sensor_reliability: float = 0.25
    """Away from edges a disagreeing sensor value is kept when ``r_c`` is at least this (rule 3)."""
    agree_value: str = "sensor"
    """Where sensor and estimate agree (rule 1): ``"sensor"`` keeps the sensor's value, ``"estimate"``
    takes the estimate's (denoised when the estimate is the refined depth)."""

    def __post_init__(self) -> None:
        if not 0 < self.min_range_m < self.max_range_m:
            raise ValueError(f"need 0 < min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")
        if self.agree_value not in ("sensor", "estimate"):
            raise ValueError(f"agree_value must be 'sensor' or 'estimate', got {self.agree_value!r}")
        if self.edge_band_px < 0:
            raise ValueError(f"edge_band_px must be >= 0, got {self.edge_band_px}")


@dataclass(frozen=True)
class FusedDepth:
    """Result of :func:`fuse_depth`."""

    depth_m: np.ndarray
    """float32 (H, W) fused depth, metres, 0 = unknown."""
    source: np.ndarray = field(repr=False)
    """uint8 (H, W): 0 none, 1 sensor (aligned captured depth), 2 estimate."""


def sensor_reliability(depth_m: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """Eq. 5.7: ``(MaxD^2 - d^2) / (MaxD^2 - MinD^2)`` inside ``(MinD, MaxD)``, else 0 (float32)."""
    d = np.asarray(depth_m, dtype=np.float64)
    r = (max_range_m ** 2 - d * d) / (max_range_m ** 2 - min_range_m ** 2)
    return np.where((d > min_range_m) & (d < max_range_m), r, 0.0).astype(np.float32)


def _edge_band(e: np.ndarray, edge_rel: float, band_px: int) -> np.ndarray:
    valid = e > 0
    edge = np.zeros(e.shape, bool)
    for a, b, sl_a, sl_b in ((e[:, 1:], e[:, :-1], (slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                             (e[1:, :], e[:-1, :], (slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        both = (a > 0) & (b > 0)
        step = both & (np.abs(a - b) > edge_rel * np.minimum(a, b))
        edge[sl_a] |= step
        edge[sl_b] |= step
    edge &= valid
    if band_px > 0 and edge.any():
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * band_px + 1, 2 * band_px + 1))
        edge = cv2.dilate(edge.astype(np.uint8), k) > 0
    return edge


def fuse_depth(aligned_m: np.ndarray, estimated_m: np.ndarray, config: FuseConfig = FuseConfig(),
               scale: float = 1.0) -> FusedDepth:
    """Fuse aligned captured depth with the estimated depth (rule in the module docstring). Pure.

    Args:
        aligned_m: float32 (H, W) captured depth aligned to the colour image (0 = none).
        estimated_m: float32 (H, W) estimated depth (0 = none); multiplied by ``scale`` first.
        config: :class:`FuseConfig`.
        scale: metric scale of the estimate (``AlignedDepth.scale``).
    """
    a = np.nan_to_num(np.asarray(aligned_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    e = np.nan_to_num(np.asarray(estimated_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0) * np.float32(scale)
    if a.shape != e.shape or a.ndim != 2:
        raise ValueError(f"fuse_depth: aligned {a.shape} and estimated {e.shape} must be the same (H, W)")
    a[a < 0] = 0
    e[e < 0] = 0
    cfg = config
    va, ve = a > 0, e > 0
    r_c = sensor_reliability(a, cfg.min_range_m, cfg.max_range_m)
    both = va & ve
    agree = both & (np.abs(a - e) <= cfg.agree_rel * e)
    near_edge = _edge_band(e, cfg.edge_rel, cfg.edge_band_px)
    take_a = (agree if cfg.agree_value == "sensor" else np.zeros_like(agree)) | (both & ~agree & ~near_edge & (r_c >= cfg.min_sensor_reliability)) | (va & ~ve & (r_c > 0))
    take_e = ve & ~take_a
    out = np.where(take_a, a, np.where(take_e, e, 0.0)).astype(np.float32)
    src = np.where(take_a, SOURCE_SENSOR, np.where(take_e, SOURCE_ESTIMATE, SOURCE_NONE)).astype(np.uint8)
    return FusedDepth(out, src)
