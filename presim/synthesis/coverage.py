"""Is a render pose covered by the capture? (``presim render`` warns when it is not.)

:func:`far_poses` reports frames whose camera centre is more than ``far_m`` from every captured one or whose hole
fraction before filling exceeds ``max_hole_frac`` (such images are mostly filled, or black with ``--no-fill``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FarPose", "far_poses"]


@dataclass(frozen=True)
class FarPose:
    frame: int
    distance_m: float
    """Distance to the nearest captured camera centre."""
    nearest_view: int
    hole_frac: float
    """Fraction of the image no captured view covered (before hole filling)."""

    def __str__(self) -> str:
        return (f"frame {self.frame}: pose is {self.distance_m:.2f} m from the nearest captured view "
                f"(frame {self.nearest_view}); {self.hole_frac:.0%} of the image had no captured pixel "
                "before hole filling")


def far_poses(scene, T_world_cams: np.ndarray, hole_fracs, far_m: float = 1.0,
              max_hole_frac: float = 0.5) -> list[FarPose]:
    """Frames more than ``far_m`` from every captured view or with hole fraction above ``max_hole_frac``."""
    centres = np.asarray(scene.camera_centres, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(T_world_cams, dtype=np.float64).reshape(-1, 4, 4)
    out = []
    for i, (Ti, hole) in enumerate(zip(T, hole_fracs)):
        d = np.linalg.norm(centres - Ti[:3, 3], axis=1) if len(centres) else np.array([np.inf])
        k = int(np.argmin(d))
        if d[k] > far_m or float(hole) > max_hole_frac:
            out.append(FarPose(i, float(d[k]), k, float(hole)))
    return out
