"""Fixed-rate loop that keeps its period by deadline, not by sleep(period), and measures jitter.

A loop that sleeps `period` after its work drifts by the work time every cycle; this one
schedules tick k at start + k*period and, if it falls more than one period behind, skips
ahead (counting the overrun) rather than bursting to catch up.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

import numpy as np


class LoopStats:
    """Rolling period error and work time (ms) over the last `window` ticks."""

    def __init__(self, window: int = 500):
        self.period_error_ms: deque[float] = deque(maxlen=window)
        self.work_ms: deque[float] = deque(maxlen=window)
        self.ticks = 0
        self.overruns = 0

    def summary(self) -> dict[str, float]:
        if not self.period_error_ms:
            return {"ticks": self.ticks, "overruns": self.overruns}
        err = np.abs(np.fromiter(self.period_error_ms, float))
        work = np.fromiter(self.work_ms, float)
        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "period_error_p50_ms": round(float(np.percentile(err, 50)), 3),
            "period_error_p99_ms": round(float(np.percentile(err, 99)), 3),
            "work_p50_ms": round(float(np.percentile(work, 50)), 3),
            "work_p99_ms": round(float(np.percentile(work, 99)), 3),
        }


class RateLoop:
    """Calls `fn()` at `rate_hz` in its own thread until `stop()`; exceptions are reported, not fatal."""

    def __init__(self, rate_hz: float, fn: Callable[[], None], name: str = "loop",
                 on_error: Callable[[BaseException], None] | None = None):
        if rate_hz <= 0:
            raise ValueError("rate_hz must be > 0")
        self.period_s = 1.0 / rate_hz
        self.fn = fn
        self.name = name
        self.on_error = on_error
        self.stats = LoopStats()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> "RateLoop":
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout_s)

    def set_rate(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz

    def _run(self) -> None:
        next_t = time.perf_counter()
        prev_t: float | None = None
        while not self._stop.is_set():
            now = time.perf_counter()
            if next_t > now:
                if self._stop.wait(next_t - now):
                    break
                now = time.perf_counter()
            if prev_t is not None:
                self.stats.period_error_ms.append((now - prev_t - self.period_s) * 1e3)
            prev_t = now
            try:
                self.fn()
            except BaseException as e:  # noqa: BLE001 - a loop must survive its body
                if self.on_error:
                    self.on_error(e)
            done = time.perf_counter()
            self.stats.work_ms.append((done - now) * 1e3)
            self.stats.ticks += 1
            next_t += self.period_s
            if done - next_t > self.period_s:
                self.stats.overruns += 1
                next_t = done + self.period_s
