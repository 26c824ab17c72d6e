"""16-bit depth PNGs: the one encoder and its overflow rule.

A PNG value ``v`` stores ``v * depth_scale_mm`` millimetres (BOP's ``depth_scale``; 1.0 = plain
millimetres as KinectFusion / 7-Scenes folders and ``presim render`` write, 0.1 = BOP's PBR data).

The rule, for every pixel of a float32 z-depth map in metres (0 = invalid):

- ``v = round(depth_m * 1000 / depth_scale_mm)`` in float64, rounding half to even (``np.round``);
- values that do not fit in 1..65535 become 0 = invalid: depths that round to 0, negative, NaN, and
  depths beyond ``65535 * depth_scale_mm`` mm (65.535 m at 1 mm, 6.5535 m at 0.1 mm);
- the number of pixels lost to the upper bound (``+inf`` included) is returned as ``n_clipped``,
  so a writer can report it; values are never wrapped or saturated.

Readers turn 0 back into invalid; the ``kinfu`` importer also treats 65535 as invalid (the Kinect
"no return" code), so a depth of exactly 65535 units is lost there too.
"""

from __future__ import annotations

import numpy as np

from presim.formats.png import encode_png

__all__ = ["DEPTH_PNG_MAX", "depth_to_png_u16", "encode_depth_png"]

DEPTH_PNG_MAX = 65535
"""Largest value a 16-bit depth PNG holds."""


def depth_to_png_u16(depth_m: np.ndarray, depth_scale_mm: float = 1.0) -> tuple[np.ndarray, int]:
    """(H, W) float depth in metres -> ``(uint16 (H, W) PNG values, n_clipped)`` by the module's rule.

    Example:
        >>> v, n = depth_to_png_u16(np.array([[0.0, 1.2345, 70.0]]), 1.0)
        >>> v.tolist(), n
        ([[0, 1234, 0]], 1)
    """
    if not depth_scale_mm > 0:
        raise ValueError(f"depth_scale_mm must be positive, got {depth_scale_mm}")
    q = np.round(np.asarray(depth_m, dtype=np.float64) * 1000.0 / depth_scale_mm)  # metres -> mm -> units
    over = q > DEPTH_PNG_MAX
    q[over | ~np.isfinite(q) | (q < 0)] = 0
    return q.astype(np.uint16), int(np.count_nonzero(over))


def encode_depth_png(depth_m: np.ndarray, depth_scale_mm: float = 1.0,
                     compression: int | None = None) -> tuple[bytes, int]:
    """16-bit PNG bytes of ``depth_m`` by the module's rule; returns ``(bytes, n_clipped)``.
    ``compression``: OpenCV PNG level 0-9 (None = OpenCV's default)."""
    values, n_clipped = depth_to_png_u16(depth_m, depth_scale_mm)
    return encode_png(values, compression), n_clipped
