"""The Renderer's view cache (presim/lru.py, LRUCache, owned by the executor): LRU bound, views built ahead in a
background thread, and images that do not depend on who built a view."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from presim.capture.scene import SceneError
from presim.geometry import Intrinsics, look_at
from presim.imaging.pool import pool_depth_aware
from presim.lru import LRUCache
from presim.numba_threads import serial_kernels
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer
from presim.testing import rect_scene as S


class _Item:
    def __init__(self, name: str, nbytes: int = 10):
        self.name, self.nbytes = name, nbytes


def test_lru_bound_in_bytes_and_one_build_per_key():
    c = LRUCache(limit_bytes=25)
    calls = []

    def build(k):
        calls.append(k)
        return _Item(k)

    a = c.get("a", lambda: build("a"))
    assert c.get("a", lambda: build("a")) is a and calls == ["a"]
    c.get("b", lambda: build("b"))
    c.get("a", lambda: build("a"))  # a is now the most recent
    c.get("c", lambda: build("c"))  # 30 bytes > 25: the least recent (b) goes
    assert "b" not in c and "a" in c and "c" in c and c.nbytes == 20 and len(c) == 2
    big = LRUCache(limit_bytes=5)
    big.get("x", lambda: _Item("x", 100))
    assert "x" in big  # the newest view is always kept


def test_serial_pool_kernel_equals_the_parallel_one():
    rng = np.random.default_rng(3)
    d = rng.uniform(0.5, 3.0, (37, 52)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = 0.0
    c = rng.integers(0, 256, (37, 52, 3), dtype=np.uint8)
    for tol in (0.0, 0.02, 0.5):
        a = pool_depth_aware(d, c, tol)
        with serial_kernels():
            b = pool_depth_aware(d, c, tol)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
