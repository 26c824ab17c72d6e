"""Photometric calibration of a capture (a sub-package above ``capture``; docs/layout.md).

:func:`calibrate_photometric` solves one colour transform per frame from depth-reprojected
correspondences (:mod:`presim.photometric.calibrate`); :mod:`presim.photometric.apply` applies a
calibration to a frame's pixels at render time (the renderer imports it). The result type,
:class:`~presim.capture.calibration.PhotometricCalib`, lives in the leaf module
:mod:`presim.capture.calibration`, so the scene and its store read a calibration without importing
this sub-package.
"""

from presim.photometric.calibrate import PhotometricConfig, calibrate_photometric

__all__ = ["PhotometricConfig", "calibrate_photometric"]
