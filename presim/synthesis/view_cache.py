"""Cache of prepared views (:class:`presim.synthesis.warp.ViewPoints`): LRU, bounded in bytes.

Owned by :class:`presim.synthesis.execution.Executor`. A prepared view costs 2-9 ms at 640x480 (read, pool
the level, back-project, sort by layer), so each is built once per level and kept until the bound is
reached. (Building a frame's later candidates on a background thread measured 1.00-1.04x on the render and
PointNav cases of ``benchmarks/bench_ab.py`` and was removed.)
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable, Hashable

__all__ = ["ViewCache"]


class ViewCache:
    """LRU cache of prepared views bounded in bytes (each value has ``.nbytes``); the newest always stays."""

    def __init__(self, limit_bytes: float):
        self.limit_bytes = float(limit_bytes)
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self._bytes = 0

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached views."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def peek(self, key: Hashable) -> Any | None:
        """The cached value of ``key`` or None, without building it or changing the LRU order."""
        return self._items.get(key)

    def get(self, key: Hashable, build: Callable[[], Any]) -> Any:
        """The value of ``key``, built with ``build()`` and cached when missing."""
        value = self._items.get(key)
        if value is not None:
            self._items.move_to_end(key)
            return value
        value = build()
        self._items[key] = value
        self._bytes += int(value.nbytes)
        while self._bytes > self.limit_bytes and len(self._items) > 1:
            _, old = self._items.popitem(last=False)
            self._bytes -= int(old.nbytes)
        return value

    def close(self) -> None:
        """Nothing to stop (kept for the executor's interface)."""
