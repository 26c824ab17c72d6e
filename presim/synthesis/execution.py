"""The executor: when and on which thread a frame's work runs; it never changes a pixel.

Frames of at most ``numba_threads.SERIAL_MAX_PIXELS`` pixels run on one numba thread (the serial twins); such a frame
leaves a core idle, so a helper thread (:mod:`presim.synthesis.warp_ahead`) warps the later candidates the
stream's previous frame drew while the loop works on the first view. Prepared views (2-9 ms each at 640x480: read,
pool the level, back-project, sort by layer) live in an :class:`~presim.lru.LRUCache`. Each mechanism is switched
by :class:`~presim.synthesis.config.PerfConfig` and earned >= 10 % on a case of ``benchmarks/bench_ab.py``."""

from __future__ import annotations

import contextlib
import os
from typing import Any, Iterator

import numpy as np

from presim.geometry import Intrinsics
from presim.lru import LRUCache
from presim.numba_threads import frame_threads, numba_threads
from presim.synthesis.config import PerfConfig, RenderConfig
from presim.synthesis.cracks import TILED_MIN_PIXELS
from presim.synthesis.pipeline import ViewImage, Workspace, banded_applies, stage_kernels
from presim.synthesis.warp_ahead import WARP_AHEAD_MIN_POINTS, WarpAhead

__all__ = ["Executor"]


class Executor:
    """Schedules one Renderer's work (one rendering thread; see the module doc)."""

    def __init__(self, perf: PerfConfig, config: RenderConfig):
        self.perf = perf
        self.kernels = stage_kernels(perf.backend, perf.torch_device)
        self.cache = LRUCache(perf.cache_mb * 2**20)
        self.workspace = Workspace()
        # Warping ahead needs the numba backend's banded crack pass, no blending (which keeps the
        # loop's own warps) and a second core.
        self._can_ahead = (perf.backend == "numba" and perf.warp_ahead and perf.threads == 0 and not config.blend
                           and banded_applies(config, config.num_layers) and (os.cpu_count() or 1) >= 2)
        self._ahead: WarpAhead | None = None
        self._ahead_on = False
        self.max_later = config.fixed_views if config.fixed_views > 0 else config.max_views

    def frame_threads(self, K: Intrinsics) -> int:
        return frame_threads(K.width, K.height, self.perf.threads)

    @contextlib.contextmanager
    def frame(self, K: Intrinsics) -> Iterator[None]:
        """A frame of size ``K`` at its numba thread count; on exit, views given to :meth:`warp_ahead` are dropped."""
        try:
            with numba_threads(self.frame_threads(K)):
                yield
        finally:
            if self._ahead_on:
                self._ahead.stop()
                self._ahead_on = False

    def ahead_possible(self, K: Intrinsics) -> bool:
        """Whether a frame of size ``K`` warps later views ahead on the helper thread."""
        return self._can_ahead and K.width * K.height < TILED_MIN_PIXELS and self.frame_threads(K) == 1

    def warp_ahead(self, views: list[Any], T_cam_world: np.ndarray, K: Intrinsics, near_m: float) -> None:
        """Hand ``views`` (prepared, likely loop order) to the helper thread for this frame (inside :meth:`frame`);
        views of fewer than ``WARP_AHEAD_MIN_POINTS`` points are left to the loop."""
        views = [v for v in views if len(v.xyz_world) >= WARP_AHEAD_MIN_POINTS]
        if not views or not self.ahead_possible(K):
            return
        if self._ahead is None:
            self._ahead = WarpAhead()
        self._ahead.start(views, T_cam_world, K, near_m)
        self._ahead_on = True

    def view_image(self, view: Any, T_cam_world: np.ndarray, K: Intrinsics, config: RenderConfig,
                   replace: np.ndarray | None, front: tuple[np.ndarray, np.ndarray] | None = None) -> ViewImage:
        """The view's image: taken from the helper thread when it warped it, else computed here; a numba view image
        also writes its front-most surface into ``front`` (blending, which keeps the helper thread off)."""
        if self._ahead_on:
            got = self._ahead.take(view)
            if got is not None:
                d, c = got
                if replace is None:  # the first view's image becomes the frame's: not the thread's buffers
                    d, c = d.copy(), c.copy()
                return ViewImage(d, c)
        self.workspace.front = front
        try:
            return self.kernels.view_image(view, T_cam_world, K, config, replace, self.workspace)
        finally:
            self.workspace.front = None

    def close(self) -> None:
        """Stop the helper threads."""
        if self._ahead is not None:
            self._ahead.close()
