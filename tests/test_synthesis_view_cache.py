"""The Renderer's view cache (presim/synthesis/view_cache.py): LRU bound, views built ahead in a
background thread, and images that do not depend on who built a view."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from presim.capture.scene import SceneError
from presim.geometry import Intrinsics, look_at
from presim.synthesis.lod import pool_depth_aware
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer
from presim.synthesis.view_cache import ViewCache
from presim.testing import rect_scene as S


class _Item:
    def __init__(self, name: str, nbytes: int = 10):
        self.name, self.nbytes = name, nbytes


def test_lru_bound_in_bytes_and_one_build_per_key():
    c = ViewCache(limit_bytes=25)
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
    big = ViewCache(limit_bytes=5)
    big.get("x", lambda: _Item("x", 100))
    assert "x" in big  # the newest view is always kept


def test_background_builds_are_taken_and_waited_for():
    c = ViewCache(limit_bytes=1e9, background=True)
    started, release = threading.Event(), threading.Event()

    def slow():
        started.set()
        assert release.wait(10)
        return _Item("slow")

    c.ahead(lambda build_ahead: (build_ahead("fast", lambda: _Item("fast")), build_ahead("slow", slow)))
    assert started.wait(10)  # "fast" is done, "slow" is being built right now
    assert c.get("fast", lambda: pytest.fail("built twice")).name == "fast"
    threading.Timer(0.05, release.set).start()
    assert c.get("slow", lambda: pytest.fail("built twice")).name == "slow"  # waited for the thread
    c.wait()
    assert c.built_ahead == 2 and c.taken_ahead == 2
    c.get("own", lambda: _Item("own"))
    assert c.built_ahead == 2 and c.taken_ahead == 2
    c.close()


def test_a_failed_background_build_is_raised_by_the_main_threads_own_build():
    c = ViewCache(limit_bytes=1e9, background=True)
    gate = threading.Event()

    def bad():
        gate.wait(10)
        raise SceneError("frame 3: corrupt (background)")

    c.ahead(lambda build_ahead: build_ahead("k", bad))
    threading.Timer(0.05, gate.set).start()

    def own():
        raise SceneError("frame 3: corrupt (main)")

    with pytest.raises(SceneError, match="main"):
        c.get("k", own)
    c.wait()
    assert "k" not in c and c.built_ahead == 0
    c.close()


def test_background_off_is_a_no_op():
    c = ViewCache(limit_bytes=1e9, background=False)
    c.ahead(lambda build_ahead: pytest.fail("ran"))
    c.wait()
    assert c.built_ahead == 0


def test_serial_pool_kernel_equals_the_parallel_one():
    rng = np.random.default_rng(3)
    d = rng.uniform(0.5, 3.0, (37, 52)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = 0.0
    c = rng.integers(0, 256, (37, 52, 3), dtype=np.uint8)
    for tol in (0.0, 0.02, 0.5):
        a, b = pool_depth_aware(d, c, tol), pool_depth_aware(d, c, tol, parallel=False)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def _path() -> list[np.ndarray]:
    return [look_at((x, -1.0, 1.25), (0.2 * x, 0.5, 0.4)) for x in np.linspace(-0.3, 0.3, 7)]


@pytest.mark.parametrize("size", [(160, 120), (40, 30)])  # level 0, and pooled levels of detail
def test_renderer_images_do_not_depend_on_views_built_ahead(size):
    K = Intrinsics.from_fov(160, 120, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(8), K)
    Kt = K.scaled(*size)
    ahead = Renderer(scene, RenderConfig(max_views=6, min_view_gain=0.0))
    plain = Renderer(scene, RenderConfig(max_views=6, min_view_gain=0.0), PerfConfig(prefetch=False))
    assert ahead.view_cache.background and not plain.view_cache.background
    for T in _path():
        a = ahead.render(T, Kt)
        ahead.view_cache.wait()  # deterministic: the thread finished this frame's wishes
        b = plain.render(T, Kt)
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        assert ahead.last.views == plain.last.views
    assert ahead.view_cache.built_ahead > 0 and ahead.view_cache.taken_ahead > 0
    assert plain.view_cache.built_ahead == 0
    ahead.view_cache.close()


def test_renderer_prefetch_only_on_the_numba_backend():
    K = Intrinsics.from_fov(32, 24, 60.0)
    scene = S.make_scene(S.room_rects(), S.orbit_poses(3), K)
    assert not Renderer(scene, RenderConfig(), PerfConfig(backend="reference")).view_cache.background
