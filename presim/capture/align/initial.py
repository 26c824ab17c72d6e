"""Initial poses for a capture that has none ("RGB-D SfM"): sequential registration by PnP.

Frame 0 is the world. Each next frame is registered to the most recent registered frames (up to
``lookback``) by the same verified matching as the alignment (SIFT, ratio test, PnP RANSAC on the
earlier frame's depth: metric, no scale ambiguity); the first that gives ``min_inliers`` chains its
pose. Frames none of them registers are reported and left out. The caller then runs
:func:`presim.capture.align.align_poses` (local groups, key poses, joint pass over nearest
neighbours, which adds the loop closures the sequential pass lacks).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from presim.capture.align.features import FeatureConfig, extract_features, match_pair
from presim.capture.scene import Scene
from presim.geometry import invert
from presim.io_utils import progress

__all__ = ["InitConfig", "estimate_initial_poses"]


@dataclass(frozen=True)
class InitConfig:
    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(prior_px=None))
    lookback: int = 5
    """Registered frames tried, most recent first."""
    min_registered_frac: float = 0.8
    """Fewer registered frames than this fraction: the import fails (nothing written)."""
    seed: int = 0


def estimate_initial_poses(scene: Scene, config: InitConfig = InitConfig()) -> tuple[np.ndarray, list[int]]:
    """(T_world_cam (N, 4, 4) with frame 0 = identity, indices of the frames registered).

    Unregistered frames keep an identity pose; the caller drops them. Raises ValueError naming the
    unregistered frames when fewer than ``min_registered_frac`` register."""
    n = len(scene)
    feats = []
    for i in progress(range(n), desc="poses: features", unit="frame"):
        c, d = scene.frames.load(i)
        feats.append(extract_features(c, d, config.features))
    T = np.tile(np.eye(4), (n, 1, 1))
    reg = [0]
    for i in progress(range(1, n), desc="poses: register", unit="frame"):
        for j in reversed(reg[-config.lookback:]):
            m = match_pair(feats[j], feats[i], scene.intrinsics[j], scene.intrinsics[i], config.features,
                           seed=config.seed * 1_000_003 + j * n + i)
            if m is not None:
                T[i] = T[j] @ invert(m.T_b_a)
                reg.append(i)
                break
    lost = [i for i in range(n) if i not in set(reg)]
    if len(reg) < config.min_registered_frac * n:
        names = ", ".join(scene.frame_ids[i] for i in lost[:10]) + (f" and {len(lost) - 10} more" if len(lost) > 10 else "")
        raise ValueError(f"only {len(reg)} of {n} frames could be registered (need {config.min_registered_frac:.0%}); "
                         f"not registered: {names}")
    return T, reg
