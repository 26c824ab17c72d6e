"""Photometric calibration of a capture (a sub-package above ``capture``; docs/layout.md).

:func:`calibrate_photometric` solves one colour transform per frame from depth-reprojected
correspondences (:mod:`presim.photometric.calibrate`); :mod:`presim.photometric.apply` applies a
calibration to a frame's pixels at render time. The result type,
:class:`~presim.capture.calibration.PhotometricCalib`, lives in the leaf module
:mod:`presim.capture.calibration`, so the scene and its store read a calibration without importing
this sub-package. The solver's names are imported on first use (a module ``__getattr__``), so the
renderer, which imports :mod:`presim.photometric.apply`, never loads the solver.
"""

import importlib

__all__ = ["PhotometricConfig", "calibrate_photometric"]


def __getattr__(name: str):
    if name in __all__:
        return getattr(importlib.import_module("presim.photometric.calibrate"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
