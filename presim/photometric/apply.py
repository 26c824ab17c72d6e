"""The photometric colour model applied at render time (the solver is :mod:`presim.photometric.calibrate`).

A capture frame's pixels are mapped to the output exposure when its view is prepared: per channel
``gain_o * (x - bias_v) / gain_v + bias_o`` as a 256-entry table, or with the affine/vignetting model
``A_o (W(r) A_v^-1 (x - b_v)) + b_o`` (reference :func:`correct_colors`). Uncalibrated frames stay as they are."""

from __future__ import annotations

import cv2
import numpy as np

from presim.capture.calibration import vignetting_radius_sq

__all__ = ["apply_gain_bias", "gain_bias_lut", "ViewColorTransform", "output_transform",
           "vignetting_gain_map", "correct_colors", "SourceColorCorrection", "OutputVignetting", "predict_exposure",
           "apply_exposure"]


def apply_gain_bias(color: np.ndarray, gain_v: np.ndarray, bias_v: np.ndarray, gain_o: np.ndarray,
                    bias_o: np.ndarray) -> np.ndarray:
    """Reference: ``round(clip(gain_o * (color - bias_v) / gain_v + bias_o))`` per channel, uint8; a channel
    at 0 stays 0 (clipped black carries no exposure: lifting it by a bias greys out black regions)."""
    x = np.asarray(color, np.float64)
    y = np.asarray(gain_o) * (x - np.asarray(bias_v)) / np.asarray(gain_v) + np.asarray(bias_o)
    return np.where(x == 0, 0, np.clip(np.floor(y + 0.5), 0, 255)).astype(np.uint8)


def gain_bias_lut(gain_v: np.ndarray, bias_v: np.ndarray, gain_o: np.ndarray, bias_o: np.ndarray) -> np.ndarray:
    """(1, 256, 3) uint8 table of :func:`apply_gain_bias` for every 8-bit input (``cv2.LUT`` form)."""
    levels = np.repeat(np.arange(256, dtype=np.float64)[:, None], 3, axis=1)
    return apply_gain_bias(levels, gain_v, bias_v, gain_o, bias_o).reshape(1, 256, 3)


def output_transform(calib, exposure_frame: str | None) -> tuple[np.ndarray, np.ndarray]:
    """``(A_o (3, 3), b_o (3,))`` of the output: the scene mean (identity) or frame ``exposure_frame``'s."""
    if exposure_frame is None:
        return np.eye(3), np.zeros(3)
    try:
        return calib.forward(calib.index(exposure_frame))
    except KeyError:
        raise ValueError(f"exposure_frame {exposure_frame!r} is not a frame of the photometric calibration") from None


class ViewColorTransform:
    """``(view_idx, color) -> color``: view ``view_idx`` (scene position) mapped from its own exposure to the
    output exposure through a cached per-view lookup table (per-channel path of :class:`SourceColorCorrection`)."""

    def __init__(self, calib, frame_ids: list[str], exposure_frame: str | None = None):
        self.calib = calib
        self.frame_ids = list(frame_ids)
        A_o, self.bias_o = output_transform(calib, exposure_frame)
        self.gain_o = np.diag(A_o)
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


def vignetting_gain_map(K, vignetting: tuple[float, float] | None) -> np.ndarray | None:
    """float32 (H, W) ``W(r) = 1 + k1 r^2 + k2 r^4`` of every pixel of a camera (None: no term)."""
    if vignetting is None:
        return None
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    r2 = vignetting_radius_sq(np.stack([u.ravel(), v.ravel()], axis=1), K).reshape(K.height, K.width)
    return (1.0 + vignetting[0] * r2 + vignetting[1] * r2 ** 2).astype(np.float32)


def correct_colors(color: np.ndarray, A_v: np.ndarray, b_v: np.ndarray, A_o: np.ndarray, b_o: np.ndarray,
                   gain_map: np.ndarray | None = None) -> np.ndarray:
    """Reference: ``round(clip(A_o (g A_v^-1 (color - b_v)) + b_o))``, ``g`` = ``gain_map`` (H, W) or 1; uint8;
    a channel at 0 stays 0 (clipped black, as :func:`apply_gain_bias`)."""
    black = np.asarray(color) == 0
    x = np.asarray(color, np.float64) - np.asarray(b_v, np.float64)
    rad = x @ np.linalg.inv(np.asarray(A_v, np.float64)).T
    if gain_map is not None:
        rad = rad * np.asarray(gain_map, np.float64)[..., None]
    y = rad @ np.asarray(A_o, np.float64).T + np.asarray(b_o, np.float64)
    return np.where(black, 0, np.clip(np.floor(y + 0.5), 0, 255)).astype(np.uint8)


class SourceColorCorrection:
    """``(view_idx, color) -> color`` on a capture frame's pixels before warping: calibration transform and
    vignetting mapped to the output exposure (applied when a view is prepared; uncalibrated frames unchanged)."""

    def __init__(self, calib, frame_ids: list[str], intrinsics, exposure_frame: str | None = None):
        self.calib = calib
        self.frame_ids = list(frame_ids)
        self.intrinsics = intrinsics
        self.A_o, self.b_o = output_transform(calib, exposure_frame)
        self._maps: dict = {}
        # Per-channel gain and bias without vignetting: per-view lookup tables (exact, fast).
        self._lut = ViewColorTransform(calib, frame_ids, exposure_frame) if calib.per_channel else None

    def __call__(self, view_idx: int, color: np.ndarray) -> np.ndarray:
        if self._lut is not None:
            return self._lut(view_idx, color)
        try:
            r = self.calib.index(self.frame_ids[view_idx])
        except KeyError:
            return color
        K = self.intrinsics[view_idx]
        key = (K.width, K.height, K.cx, K.cy)
        if key not in self._maps:
            self._maps[key] = vignetting_gain_map(K, self.calib.vignetting)
        A_v, b_v = self.calib.forward(r)
        return correct_colors(color, A_v, b_v, self.A_o, self.b_o, self._maps[key])


class OutputVignetting:
    """Puts the matched frame's vignetting back on a rendered image: ``(c - b_o) / W(r) + b_o`` per pixel."""

    def __init__(self, calib, exposure_frame: str):
        self.vignetting = calib.vignetting
        self.b_o = output_transform(calib, exposure_frame)[1]
        self._maps: dict = {}

    def __call__(self, color: np.ndarray, K) -> np.ndarray:
        key = (K.width, K.height, K.cx, K.cy)
        if key not in self._maps:
            self._maps[key] = 1.0 / vignetting_gain_map(K, self.vignetting)
        return correct_colors(color, np.eye(3), self.b_o, np.eye(3), self.b_o, self._maps[key])


def predict_exposure(calib, rows: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The exposure a rendered image takes when no real image exists at its pose: the weighted mean
    of the forward transforms ``(A, b)`` of the capture frames it is made of (``rows`` of the
    calibration, ``weights`` >= 0, e.g. each view's share of the image's pixels). When every frame
    has the same transform, that transform. None without weight."""
    w = np.asarray(weights, np.float64)
    if len(w) == 0 or not w.sum() > 0:
        return None
    w = w / w.sum()
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for r, wi in zip(rows, w):
        A_r, b_r = calib.forward(int(r))
        A += wi * np.asarray(A_r, np.float64)
        b += wi * np.asarray(b_r, np.float64)
    return A, b


def apply_exposure(color: np.ndarray, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``round(clip(A x + b))`` per pixel (x at the capture's mean exposure, the renderer's working
    exposure); a 256-entry table per channel when ``A`` is diagonal. Reference: :func:`correct_colors`
    with ``A_v = I, b_v = 0``."""
    A = np.asarray(A, np.float64)
    if np.count_nonzero(A - np.diag(np.diag(A))) == 0:
        return cv2.LUT(np.ascontiguousarray(color), gain_bias_lut(np.ones(3), np.zeros(3), np.diag(A), np.asarray(b)))
    return correct_colors(color, np.eye(3), np.zeros(3), A, b)
