"""The RGB-D frame: what the renderer synthesizes and the simulated camera, recorder and dataset generator carry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from presim.geometry import Intrinsics

__all__ = ["RGBD"]


@dataclass(frozen=True)
class RGBD:
    """A synthesized RGB-D image at one camera pose; ``color`` and ``depth_m`` are complete unless filling is off."""

    color: np.ndarray
    """uint8 (H, W, 3) RGB."""
    depth_m: np.ndarray
    """float32 (H, W) z-depth in metres (0 where nothing is known and filling is off)."""
    valid: np.ndarray
    """bool (H, W): True where the pixel was synthesized from captured views (not filled)."""
    source_view: np.ndarray
    """int32 (H, W): scene frame index of the pixel's source view, -1 if none."""
    K: Intrinsics
    T_world_cam: np.ndarray
    """4x4 camera-to-world pose the image was rendered at."""
    hole_frac_before_fill: float = 0.0
    """Fraction of pixels no view covered, before hole filling."""
