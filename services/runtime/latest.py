"""Newest-wins processing for perception services: a slot that holds at most one pending input
and one worker thread that processes it.

Why: a scan or frame that arrives while the previous one is being processed must never queue
(queues turn a slow stage into unbounded latency on a 2-core machine). The newer input replaces
the pending one and the replaced one is counted as dropped, so diagnostics show the real rate.
"""
from __future__ import annotations

import threading
from typing import Callable, Generic, TypeVar

T = TypeVar("T")


class LatestWorker(Generic[T]):
    """`offer(item)` from any thread; `fn(item)` runs on the worker thread for the newest item.
    Exceptions from `fn` go to `on_error` and the worker keeps running."""

    def __init__(self, fn: Callable[[T], None], name: str,
                 on_error: Callable[[BaseException], None] | None = None):
        self.fn, self.on_error = fn, on_error
        self.processed = 0
        self.dropped = 0
        self._pending: T | None = None
        self._cond = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, item: T) -> None:
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = item
            self._cond.notify()

    def stop(self, timeout_s: float = 1.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
                item, self._pending = self._pending, None
            try:
                self.fn(item)
            except Exception as e:  # noqa: BLE001 - one bad input must not stop the worker
                if self.on_error:
                    self.on_error(e)
            self.processed += 1
