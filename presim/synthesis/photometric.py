"""Per-view photometric correction at render time (the apply half of :mod:`presim.capture.photometric`).

A scene calibrated by ``presim photometric`` carries, per frame ``v``, the forward model
``observed_v = gain_v * radiance + bias_v`` (per channel). A pixel warped from view ``v`` is mapped
to the output exposure ``(gain_o, bias_o)``::

    out = gain_o * (observed_v - bias_v) / gain_v + bias_o

with ``(gain_o, bias_o) = (1, 0)`` for the scene's mean exposure (default) or a frame's own
transform to match that frame (``RenderConfig.exposure_frame``). The map is per channel and its
input is 8-bit, so it is applied as a 256-entry lookup table per channel (``cv2.LUT``, ~0.3 ms per
640x480 view image), built once per view and cached: the per-frame cost is one LUT pass per
warped view. :func:`apply_gain_bias` is the float reference the tables are tested against.

The Renderer passes :class:`ViewColorTransform` to the core's ``color_transform`` hook
(:func:`presim.synthesis.core.synthesize_frame`); frames missing from the calibration are left as
they are.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["apply_gain_bias", "gain_bias_lut", "ViewColorTransform", "output_exposure"]


def apply_gain_bias(color: np.ndarray, gain_v: np.ndarray, bias_v: np.ndarray, gain_o: np.ndarray,
                    bias_o: np.ndarray) -> np.ndarray:
    """Reference: ``round(clip(gain_o * (color - bias_v) / gain_v + bias_o))`` per channel, uint8."""
    x = np.asarray(color, np.float64)
    y = np.asarray(gain_o) * (x - np.asarray(bias_v)) / np.asarray(gain_v) + np.asarray(bias_o)
    return np.clip(np.floor(y + 0.5), 0, 255).astype(np.uint8)


def gain_bias_lut(gain_v: np.ndarray, bias_v: np.ndarray, gain_o: np.ndarray, bias_o: np.ndarray) -> np.ndarray:
    """(1, 256, 3) uint8 table of :func:`apply_gain_bias` for every 8-bit input (``cv2.LUT`` form)."""
    levels = np.repeat(np.arange(256, dtype=np.float64)[:, None], 3, axis=1)
    return apply_gain_bias(levels, gain_v, bias_v, gain_o, bias_o).reshape(1, 256, 3)


def output_exposure(calib, exposure_frame: str | None) -> tuple[np.ndarray, np.ndarray]:
    """``(gain_o, bias_o)`` of the output: the scene mean (identity) or the frame ``exposure_frame``."""
    if exposure_frame is None:
        return np.ones(3), np.zeros(3)
    try:
        i = calib.index(exposure_frame)
    except KeyError:
        raise ValueError(f"exposure_frame {exposure_frame!r} is not a frame of the photometric calibration") from None
    return calib.gain[i].copy(), calib.bias[i].copy()


class ViewColorTransform:
    """``(view_idx, color) -> color`` for the core's hook: view ``view_idx`` (scene position) mapped
    from its own exposure to the output exposure through a cached per-view lookup table."""

    def __init__(self, calib, frame_ids: list[str], exposure_frame: str | None = None):
        self.calib = calib
        self.frame_ids = list(frame_ids)
        self.gain_o, self.bias_o = output_exposure(calib, exposure_frame)
        self._luts: dict[int, np.ndarray | None] = {}

    def lut(self, view_idx: int) -> np.ndarray | None:
        """The (1, 256, 3) table of view ``view_idx`` (None: not calibrated, left as is)."""
        if view_idx not in self._luts:
            try:
                r = self.calib.index(self.frame_ids[view_idx])
            except KeyError:
                self._luts[view_idx] = None
            else:
                self._luts[view_idx] = gain_bias_lut(self.calib.gain[r], self.calib.bias[r], self.gain_o, self.bias_o)
        return self._luts[view_idx]

    def __call__(self, view_idx: int, color: np.ndarray) -> np.ndarray:
        lut = self.lut(view_idx)
        if lut is None:
            return color
        return cv2.LUT(np.ascontiguousarray(color), lut)
