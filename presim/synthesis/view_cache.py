"""Cache of prepared views (:class:`presim.synthesis.warp.ViewPoints`): LRU, bounded in bytes, optionally filled ahead.

Owned by :class:`presim.synthesis.execution.Executor`. A prepared view costs 2-9 ms at 640x480 (read, pool
the level, back-project, sort by layer); :meth:`ViewCache.ahead` builds the views a frame will need in one
background thread while the main thread renders (a view in progress is waited for, one not reached yet is built
by the main thread; a job still queued when the next one arrives is dropped). The images do not depend on who
built a view; the thread runs serial ``nogil`` numba kernels (numba's ``workqueue`` layer forbids sharing the
parallel pool). Measurements: docs/synthesis.md, "Views prepared ahead".
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Hashable

__all__ = ["ViewCache"]


class ViewCache:
    """LRU cache of prepared views bounded in bytes (each value has ``.nbytes``), with background builds.

    limit_bytes: evict least recently used views above this many bytes (the newest always stays);
    background: allow :meth:`ahead` (one worker thread, started on first use).
    """

    def __init__(self, limit_bytes: float, background: bool = False):
        self.limit_bytes = float(limit_bytes)
        self.background = bool(background)
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._pending: dict[Hashable, Future] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._queued: Future | None = None  # the background thread's latest job
        self._ahead: set[Hashable] = set()  # built by the worker, not yet asked for
        self.built_ahead = 0
        """Views the background thread built."""
        self.taken_ahead = 0
        """Views the main thread took from the background thread (cached or waited for)."""

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached views."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def _insert(self, key: Hashable, value: Any, ahead: bool = False) -> Any:
        """Cache ``value`` under ``key`` (an entry already there wins; ``ahead``: built in the background)."""
        with self._lock:
            old = self._items.get(key)
            if old is not None:
                self._items.move_to_end(key)
                return old
            self._items[key] = value
            self._bytes += value.nbytes
            if ahead:
                self._ahead.add(key)
                self.built_ahead += 1
            while self._bytes > self.limit_bytes and len(self._items) > 1:
                gone_key, gone = self._items.popitem(last=False)
                self._bytes -= gone.nbytes
                self._ahead.discard(gone_key)
            return value

    def peek(self, key: Hashable) -> Any | None:
        """The view cached under ``key``, or None (nothing is built, waited for or reordered)."""
        with self._lock:
            return self._items.get(key)

    def get(self, key: Hashable, build: Callable[[], Any]) -> Any:
        """The view under ``key``: cached, built ahead, or ``build()`` now (then cached); a view another
        thread is building is waited for, not built twice."""
        with self._lock:
            v = self._items.get(key)
            if v is not None:
                self._items.move_to_end(key)
                if key in self._ahead:
                    self._ahead.discard(key)
                    self.taken_ahead += 1
                return v
            fut = self._pending.get(key)
            if fut is None:  # this thread builds it; others wait for it
                mine = self._pending[key] = Future()
                mine.set_running_or_notify_cancel()
        if fut is not None:
            try:
                v = fut.result()  # another thread is building it now
            except Exception:  # noqa: BLE001 - build it here: the same error is raised with its context
                v = None
            if v is not None:
                with self._lock:
                    if key in self._ahead:
                        self._ahead.discard(key)
                        self.taken_ahead += 1
                return self._insert(key, v)
            return self._insert(key, build())
        try:
            v = self._insert(key, build())
        except BaseException as e:
            mine.set_exception(e)
            raise
        else:
            mine.set_result(v)
            return v
        finally:
            with self._lock:
                self._pending.pop(key, None)

    def ahead(self, job: Callable[[Callable[[Hashable, Callable[[], Any]], None]], None]) -> None:
        """Run ``job(build_ahead)`` in the background thread (no-op without ``background``), dropping a job
        still queued; the job calls ``build_ahead(key, build)`` per view (``build`` must be thread-safe)."""
        if not self.background:
            return
        with self._lock:
            if self._queued is not None:
                self._queued.cancel()  # False when it already runs: then it finishes
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="presim-views")
            self._queued = self._pool.submit(job, self._build_ahead)

    def _build_ahead(self, key: Hashable, build: Callable[[], Any]) -> None:
        """Build ``key`` here unless cached or in progress; a failure is raised by the main thread's build."""
        with self._lock:
            if key in self._items or key in self._pending:
                return
            fut: Future = Future()
            fut.set_running_or_notify_cancel()
            self._pending[key] = fut
        try:
            fut.set_result(self._insert(key, build(), ahead=True))
        except Exception as e:  # noqa: BLE001 - get() builds it again and raises there
            fut.set_exception(e)
        finally:
            with self._lock:
                self._pending.pop(key, None)

    def wait(self) -> None:
        """Block until the background thread has done what was asked of it (tests, benchmarks)."""
        with self._lock:
            queued = self._queued
        if queued is not None and not queued.cancelled():
            queued.result()

    def close(self) -> None:
        """Stop the background thread (a queued job is dropped; a running one finishes)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
