"""Sharpness-aware views at render time: prefer sharp capture frames (beyond the thesis).

Each candidate frame gets a cached blur score on first use (:func:`presim.capture.sharpness.sharpness_score`,
~2 ms per VGA frame), compared among one target's candidates: :meth:`ViewSharpness.order` moves candidates below
``demote_frac`` x the best behind the sharp ones (the first warped view matters most), and
:meth:`ViewSharpness.quality` scales a view's blend weight by ``(score / best) ** gamma``.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from presim.capture.sharpness import sharpness_score

__all__ = ["ViewSharpness"]


class ViewSharpness:
    """Per-view sharpness cache + the order/quality rules for one renderer."""

    def __init__(self, load_color: Callable[[int], np.ndarray], gamma: float = 2.0, demote_frac: float = 0.85):
        self._load_color = load_color
        self.gamma = float(gamma)
        self.demote_frac = float(demote_frac)
        self._scores: dict[int, float] = {}
        self._best = 1.0

    def score(self, v: int) -> float:
        """Sharpness score of view ``v`` (computed on first use)."""
        s = self._scores.get(v)
        if s is None:
            s = self._scores[v] = sharpness_score(self._load_color(v))
        return s

    def order(self, candidates: Sequence[int]) -> np.ndarray:
        """int64 permutation of ``candidates`` moving blurred ones (score < demote_frac x best) behind the sharp
        ones, order kept within each group; sets the best score :meth:`quality` uses."""
        cand = [int(v) for v in candidates]
        if not cand:
            return np.zeros(0, np.int64)
        sc = np.array([self.score(v) for v in cand])
        self._best = max(float(sc.max()), 1e-6)
        blurred = sc < self.demote_frac * self._best
        return np.concatenate([np.flatnonzero(~blurred), np.flatnonzero(blurred)]).astype(np.int64)

    def quality(self, v: int) -> float:
        """Blend weight factor ``(score / best candidate score) ** gamma`` (<= 1)."""
        return float(min(1.0, self.score(v) / self._best) ** self.gamma)
