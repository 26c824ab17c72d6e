"""Bounded hand-off between the step loop and a slow consumer (recorder, viewer, ROS publisher).

The loop must never wait for a sink: ``put`` appends to a bounded deque and, when it is full, drops
the OLDEST item (the newest state is the one a live consumer wants) and counts the drop. One worker
thread per sink consumes items in order. ``close`` drains what is queued (up to a timeout), joins
the worker, and reports the counts; an exception in the worker is kept and re-raised by ``close``
so a failing recorder is not silent.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

from presim.sim.types import SimInfo, Sink, StepResult

__all__ = ["QueueStats", "BoundedWorker", "QueuedSink"]

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass(frozen=True)
class QueueStats:
    """What happened to the items handed to a :class:`BoundedWorker`."""

    name: str
    put: int
    """Items offered by the producer."""
    done: int
    """Items the consumer processed."""
    dropped: int
    """Items dropped because the queue was full (oldest first) or left when the drain timed out."""
    max_depth: int
    """Largest queue length seen."""

    def summary(self) -> str:
        return (f"{self.name}: {self.done}/{self.put} steps written, {self.dropped} dropped "
                f"(queue full, oldest first), max queue depth {self.max_depth}")


class BoundedWorker(Generic[T]):
    """A worker thread fed through a bounded drop-oldest queue.

    Example:
        >>> out = []
        >>> w = BoundedWorker("demo", out.append, maxlen=4)
        >>> for i in range(3): w.put(i)
        >>> w.close().done, out
        (3, [0, 1, 2])
    """

    def __init__(self, name: str, consume: Callable[[T], None], maxlen: int = 16):
        if maxlen < 1:
            raise ValueError(f"{name}: queue length must be >= 1, got {maxlen}")
        self.name = name
        self._consume = consume
        self._items: deque[T] = deque()
        self._maxlen = int(maxlen)
        self._cv = threading.Condition()
        self._closing = False
        self._busy = False
        self._put = self._done = self._dropped = self._max_depth = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"presim-{name}", daemon=True)
        self._thread.start()

    def put(self, item: T) -> None:
        """Queue ``item``; never blocks. Drops the oldest queued item when full."""
        with self._cv:
            if self._closing:
                raise RuntimeError(f"{self.name}: put after close")
            self._put += 1
            if len(self._items) >= self._maxlen:
                self._items.popleft()
                self._dropped += 1
            self._items.append(item)
            self._max_depth = max(self._max_depth, len(self._items))
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._items and not self._closing:
                    self._cv.wait()
                if not self._items:
                    return
                item = self._items.popleft()
                self._busy = True
            try:
                if self.error is None:
                    self._consume(item)
                    self._done += 1
                else:
                    self._dropped += 1
            except BaseException as e:  # keep it for close(); later items are dropped
                log.error("%s: consumer failed: %s", self.name, e)
                self.error = e
                self._dropped += 1
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def flush(self, timeout_s: float = 30.0) -> bool:
        """Wait until the queue is empty and the consumer idle. True when it got there in time."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._items or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def close(self, timeout_s: float = 60.0) -> QueueStats:
        """Drain (at most ``timeout_s``), stop the worker and return the counts."""
        with self._cv:
            self._closing = True
            self._cv.notify_all()
        self._thread.join(timeout_s)
        with self._cv:
            if self._thread.is_alive():  # consumer stuck: whatever is left is lost
                self._dropped += len(self._items)
                self._items.clear()
            return self.stats()

    def stats(self) -> QueueStats:
        return QueueStats(self.name, self._put, self._done, self._dropped, self._max_depth)


class QueuedSink:
    """Wraps a synchronous sink so ``on_step`` only queues (drop-oldest); the sink runs in a worker.

    ``open`` runs synchronously (the inner sink must be ready before the first step); ``close``
    drains the queue, closes the inner sink in the caller's thread, prints a one-line report to the
    log and re-raises a worker error. ``stats`` holds the final :class:`QueueStats`.
    """

    def __init__(self, inner: Sink, name: str, maxlen: int = 16):
        self.inner = inner
        self.name = name
        self.maxlen = maxlen
        self._worker: BoundedWorker[StepResult] | None = None
        self.stats: QueueStats | None = None

    def open(self, info: SimInfo) -> None:
        self.inner.open(info)
        self._worker = BoundedWorker(self.name, self.inner.on_step, self.maxlen)

    def on_step(self, result: StepResult) -> None:
        if self._worker is None:
            raise RuntimeError(f"{self.name}: on_step before open")
        self._worker.put(result)

    def flush(self, timeout_s: float = 30.0) -> bool:
        return self._worker.flush(timeout_s) if self._worker is not None else True

    def close(self) -> None:
        if self._worker is None:
            self.inner.close()
            return
        worker, self._worker = self._worker, None
        try:
            self.stats = worker.close()
        finally:
            self.inner.close()
        msg = self.stats.summary()
        (log.warning if self.stats.dropped else log.info)(msg)
        if worker.error is not None:
            raise RuntimeError(f"{self.name} failed: {worker.error}") from worker.error
