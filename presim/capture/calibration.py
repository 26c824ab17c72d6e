"""Photometric calibration types: what a render reads of a capture's colour calibration.

A leaf module (numpy only) so that the scene (:mod:`presim.capture.scene`) and its store read a
calibration without importing :mod:`presim.photometric`, the sub-package above ``capture`` that
estimates it and applies it at render time (:mod:`presim.photometric.apply`).

- :class:`PhotometricCalib`: per-frame colour transforms (forward model ``observed = gain *
  radiance + bias``, or an affine colour matrix), keyed by frame id; stored with a scene as
  ``photometric.json`` (:func:`presim.capture.store.save_photometric`).
- :func:`vignetting_radius_sq`: the normalised radius of the shared vignetting term.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PHOTOMETRIC_MODELS", "PHOTOMETRIC_FORMAT", "PHOTOMETRIC_VERSION", "PhotometricCalib",
           "vignetting_radius_sq"]

PHOTOMETRIC_MODELS = ("gain_bias", "gain", "affine")
PHOTOMETRIC_FORMAT = "presim-photometric"
PHOTOMETRIC_VERSION = 1


@dataclass(frozen=True)
class PhotometricCalib:
    """Per-frame colour transforms of a capture (forward model ``observed = gain * radiance + bias``)."""

    frame_ids: tuple[str, ...]
    """Frame ids the rows belong to (a render looks transforms up by id)."""
    gain: np.ndarray
    """float64 (N, 3) per-channel gain (RGB); mean over frames = 1."""
    bias: np.ndarray
    """float64 (N, 3) per-channel bias, 8-bit levels; mean over frames = 0."""
    model: str = "gain_bias"
    """Transform family (:data:`PHOTOMETRIC_MODELS`)."""
    stats: dict = field(default_factory=dict)
    """How the solve went: pairs, samples, residual RMS before / after (levels), seconds."""
    matrix: np.ndarray | None = None
    """Model ``"affine"``: float64 (N, 3, 3) forward colour matrices ``A`` (``observed = A @
    radiance + bias``; ``gain`` is their diagonal; mean over frames = identity). None otherwise."""
    vignetting: tuple[float, float] | None = None
    """Shared radial vignetting ``(k1, k2)``: a pixel at normalised radius ``r`` (distance to the
    principal point / half the image diagonal) records ``radiance / (1 + k1 r^2 + k2 r^4)`` before
    the frame's colour transform; None = no vignetting term."""

    def __post_init__(self) -> None:
        n = len(self.frame_ids)
        if self.gain.shape != (n, 3) or self.bias.shape != (n, 3):
            raise ValueError(f"PhotometricCalib: gain/bias must be ({n}, 3), got {self.gain.shape}/{self.bias.shape}")
        if self.model not in PHOTOMETRIC_MODELS:
            raise ValueError(f"PhotometricCalib: model must be one of {PHOTOMETRIC_MODELS}")
        if not (np.all(np.isfinite(self.gain)) and np.all(self.gain > 0)):
            raise ValueError(f"PhotometricCalib: gains must be finite and > 0, got {self._bad_rows(self.gain, True)}")
        if not np.all(np.isfinite(self.bias)):
            raise ValueError(f"PhotometricCalib: biases must be finite, got {self._bad_rows(self.bias, False)}")
        if (self.model == "affine") != (self.matrix is not None):
            raise ValueError("PhotometricCalib: matrix is given exactly for model 'affine'")
        if self.matrix is not None and (np.shape(self.matrix) != (n, 3, 3) or not np.all(np.isfinite(self.matrix))
                                        or np.any(np.abs(np.linalg.det(self.matrix)) < 1e-6)):
            raise ValueError(f"PhotometricCalib: matrix must be ({n}, 3, 3), finite and invertible")
        if self.vignetting is not None and (len(self.vignetting) != 2 or not np.all(np.isfinite(self.vignetting))):
            raise ValueError("PhotometricCalib: vignetting must be two finite numbers (k1, k2)")

    def _bad_rows(self, values: np.ndarray, positive: bool) -> str:
        """``frame_id=[values]`` of the first rows that break the rule (for the error message)."""
        bad = ~np.isfinite(values).all(axis=1)
        if positive:
            bad |= ~(values > 0).all(axis=1)
        rows = np.flatnonzero(bad)[:3]
        return ", ".join(f"{self.frame_ids[r]}={values[r].tolist()}" for r in rows)

    @property
    def per_channel(self) -> bool:
        """True when the transform is a per-channel gain and bias with no vignetting (a lookup table
        per view applies it after warping); False: applied to the source pixels (affine / vignetting)."""
        return self.matrix is None and self.vignetting is None

    def forward(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        """``(A (3, 3), b (3,))`` of frame row ``row``: ``observed = A @ radiance + b``."""
        A = self.matrix[row] if self.matrix is not None else np.diag(self.gain[row])
        return np.asarray(A, np.float64), np.asarray(self.bias[row], np.float64)

    def index(self, frame_id: str) -> int:
        """Row of ``frame_id`` (KeyError naming it when absent)."""
        lut = self.__dict__.get("_lut")
        if lut is None:
            lut = {f: i for i, f in enumerate(self.frame_ids)}
            object.__setattr__(self, "_lut", lut)
        if frame_id not in lut:
            raise KeyError(f"photometric calibration has no frame {frame_id!r}")
        return lut[frame_id]

    def to_json(self) -> dict:
        frames = [{"frame_id": f, "gain": [float(x) for x in self.gain[i]], "bias": [float(x) for x in self.bias[i]]}
                  for i, f in enumerate(self.frame_ids)]
        if self.matrix is not None:
            for i, fr in enumerate(frames):
                fr["matrix"] = [[float(x) for x in row] for row in self.matrix[i]]
        d = {"format": PHOTOMETRIC_FORMAT, "version": PHOTOMETRIC_VERSION, "model": self.model, "stats": self.stats}
        if self.vignetting is not None:
            d["vignetting"] = [float(x) for x in self.vignetting]
        d["frames"] = frames
        return d

    @classmethod
    def from_json(cls, d: dict, where: str = "photometric.json") -> "PhotometricCalib":
        if d.get("format") != PHOTOMETRIC_FORMAT:
            raise ValueError(f"{where}: unknown format {d.get('format')!r}")
        if d.get("version") != PHOTOMETRIC_VERSION:
            raise ValueError(f"{where}: version {d.get('version')} is not supported (reads {PHOTOMETRIC_VERSION})")
        try:
            fr = d["frames"]
            model = d.get("model", "gain_bias")
            matrix = (np.array([f["matrix"] for f in fr], np.float64).reshape(len(fr), 3, 3)
                      if model == "affine" else None)
            vig = d.get("vignetting")
            return cls(tuple(str(f["frame_id"]) for f in fr),
                       np.array([f["gain"] for f in fr], np.float64).reshape(len(fr), 3),
                       np.array([f["bias"] for f in fr], np.float64).reshape(len(fr), 3),
                       model, dict(d.get("stats", {})), matrix,
                       None if vig is None else (float(vig[0]), float(vig[1])))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{where}: malformed ({type(e).__name__}: {e})") from None


def vignetting_radius_sq(uv: np.ndarray, K) -> np.ndarray:
    """Squared normalised radius ``r^2`` of pixels ``uv`` (m, 2) under intrinsics ``K``: distance to
    the principal point over half the image diagonal (``r`` = 1 at a corner of a centred image)."""
    uv = np.asarray(uv, np.float64)
    return ((uv[:, 0] - K.cx) ** 2 + (uv[:, 1] - K.cy) ** 2) / (0.25 * (K.width ** 2 + K.height ** 2))
