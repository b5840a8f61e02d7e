"""Newest-wins processing for perception services: a slot that holds at most one pending input
and one worker thread that processes it; and RateGate, which thins an input to a rate.

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
            assert item is not None     # waited for above: an offered item is never None
            try:
                self.fn(item)
            except Exception as e:  # noqa: BLE001 - one bad input must not stop the worker
                if self.on_error:
                    self.on_error(e)
            self.processed += 1


class RateGate:
    """Admits at most `rate_hz` events per second on average (a token bucket of depth 2): a source
    at exactly the rate passes whole despite jitter, a faster one is thinned evenly (12 Hz -> 10,
    not 6), and after a pause at most two events pass back to back."""

    DEPTH = 2.0

    def __init__(self, rate_hz: float):
        self.rate_hz = rate_hz
        self._tokens = self.DEPTH   # full: events exactly one period apart keep a token in reserve, so
                                    # one a little early (jitter, float rounding) still passes
        self._last_s: float | None = None
        self.admitted = 0
        self.skipped = 0

    def admit(self, now_s: float) -> bool:
        if self._last_s is not None:
            self._tokens = min(self.DEPTH, self._tokens + max(0.0, now_s - self._last_s) * self.rate_hz)
        self._last_s = now_s
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            self.admitted += 1
            return True
        self.skipped += 1
        return False
