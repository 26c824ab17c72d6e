"""A least-recently-used cache bounded in bytes (the renderer's prepared views)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable, Hashable

__all__ = ["LRUCache"]


class LRUCache:
    """Least-recently-used cache bounded in bytes (each value has ``.nbytes``); the newest value always stays."""

    def __init__(self, limit_bytes: float):
        self.limit_bytes = float(limit_bytes)
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self.nbytes = 0

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
        value = self._items[key] = build()
        self.nbytes += int(value.nbytes)
        while self.nbytes > self.limit_bytes and len(self._items) > 1:
            self.nbytes -= int(self._items.popitem(last=False)[1].nbytes)
        return value
