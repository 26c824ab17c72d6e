"""The renderer's reconstruction filter fitted on the capture itself (``presim fit-filter``).

Capture frames spread over the capture are each rendered from the *other* frames at their own pose and
intrinsics, unfiltered; then every candidate sigma filters the renders (:mod:`presim.imaging.gaussian`) and is
scored by the mean squared colour error against the real frames on the pixels a view covered. The sigma with
the lowest mean error is the scene's filter: it weighs the views' sensor noise and sub-pixel misregistration
against detail for this capture and camera, and no frame the renderer is later compared with is needed."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from presim.capture.scene import Scene
from presim.imaging.gaussian import smooth_colors
from presim.io_utils import progress
from presim.synthesis.config import RenderConfig
from presim.synthesis.renderer import Renderer

__all__ = ["SmoothFitConfig", "SmoothFit", "held_out_frames", "fit_smoothing"]


@dataclass(frozen=True)
class SmoothFitConfig:
    """What :func:`fit_smoothing` tries."""

    sigmas_px: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(21))
    """Candidate sigmas, pixels at the capture's sampling (0 = no filter)."""
    max_frames: int = 8
    """Held-out capture frames rendered (evenly spread over the capture)."""
    min_covered_frac: float = 0.2
    """A held-out frame counts when views covered at least this fraction of it."""

    def __post_init__(self) -> None:
        if not self.sigmas_px or any(not 0.0 <= s <= 8.0 for s in self.sigmas_px):
            raise ValueError(f"SmoothFitConfig: sigmas_px must be non-empty values in [0, 8], got {self.sigmas_px}")
        if self.max_frames < 1 or not 0.0 <= self.min_covered_frac < 1.0:
            raise ValueError("SmoothFitConfig: max_frames must be >= 1 and min_covered_frac in [0, 1)")


@dataclass(frozen=True)
class SmoothFit:
    """Result of :func:`fit_smoothing`."""

    sigma_px: float
    """The chosen sigma (0 when no frame could be scored)."""
    sigmas_px: list[float]
    psnr_db: list[float]
    """Mean PSNR on covered pixels over the scored frames, per candidate sigma."""
    frames: list[str]
    """Ids of the frames scored."""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def held_out_frames(n: int, max_frames: int, exclude: Sequence[int] = ()) -> list[int]:
    """Up to ``max_frames`` frame indices of ``range(n)`` outside ``exclude``, evenly spread.

    Example:
        >>> held_out_frames(10, 3, exclude=[0])
        [1, 5, 9]
    """
    pool = [i for i in range(n) if i not in set(exclude)]
    if len(pool) <= max_frames:
        return pool
    return sorted({pool[int(round(k))] for k in np.linspace(0, len(pool) - 1, max_frames)})


def fit_smoothing(scene: Scene, config: SmoothFitConfig = SmoothFitConfig(),
                  render_config: RenderConfig = RenderConfig(), exclude: Sequence[int] = ()) -> SmoothFit:
    """Fit the reconstruction filter of ``scene`` (see the module doc). Frames in ``exclude`` (indices) are
    neither rendered nor used as views (an evaluation's targets)."""
    if len(scene) - len(set(exclude)) < 2:
        raise ValueError(f"fit-filter: need at least 2 frames outside the excluded ones, the scene has {len(scene)}")
    rc = dataclasses.replace(render_config, smooth_sigma_px=0.0, fill_holes=True)
    sq = np.zeros(len(config.sigmas_px))
    scored: list[str] = []
    for i in progress(held_out_frames(len(scene), config.max_frames, exclude), desc="fit-filter", unit="frame"):
        others = [j for j in range(len(scene)) if j != i and j not in set(exclude)]
        out = Renderer(scene.subset(others), rc).render(scene.T_world_cam[i], scene.intrinsics[i])
        if out.valid.mean() < config.min_covered_frac:
            continue
        real = scene.frames.load(i)[0][out.valid].astype(np.float64)
        for k, s in enumerate(config.sigmas_px):
            diff = smooth_colors(out.color, s)[out.valid] - real
            sq[k] += 10.0 * np.log10(255.0 ** 2 / max(float(np.mean(diff * diff)), 1e-10))
        scored.append(scene.frame_ids[i])
    if not scored:
        return SmoothFit(0.0, list(config.sigmas_px), [float("nan")] * len(config.sigmas_px), [])
    psnr = sq / len(scored)
    return SmoothFit(float(config.sigmas_px[int(np.argmax(psnr))]), list(config.sigmas_px), psnr.tolist(), scored)
