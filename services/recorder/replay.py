"""Replay: republish recorded messages with their original key, encoding and timing, and drive
sim/clock from the recording's time line so services run with --sim-time follow it.

Plain logic: the publishing functions and the time source are injected (tests step it without
Zenoh); `aero replay` wires it to a session.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable

from aeroperception.schemas import Clock, Header, encode
from aeroperception.services.runtime.node import encoding_for

CLOCK_KEY = "sim/clock"
CLOCK_ENCODING = str(encoding_for(Clock))


@dataclass
class Recorded:
    key: str
    encoding: str
    payload: bytes
    log_time_ns: int


@dataclass
class ReplayStats:
    messages: int = 0
    clock_ticks: int = 0
    late_max_s: float = 0.0


class Replayer:
    """Publish `messages` (in log-time order) at `rate` x their recorded pace.

    publish(key, payload, encoding) for each message; sim/clock (stamp = recorded time of the
    replay's current instant, speed_factor = rate) every `clock_period_s` of wall time unless
    `clock` is False or the recording carries its own sim/clock (then that one is replayed)."""

    def __init__(self, publish: Callable[[str, bytes, str], None], rate: float = 1.0, clock: bool = True,
                 clock_key: str = CLOCK_KEY,
                 clock_period_s: float = 0.01, now: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, stop: Callable[[], bool] = lambda: False,
                 spin_s: float = 0.002):
        if not rate > 0:
            raise ValueError(f"rate {rate}: must be > 0")
        self.publish, self.rate, self.clock = publish, rate, clock
        self.clock_period_s, self.clock_key = clock_period_s, clock_key
        self.now, self.sleep, self.stopped, self.spin_s = now, sleep, stop, spin_s
        self.stats = ReplayStats()

    def run(self, messages: Iterable[Recorded]) -> ReplayStats:
        t0_wall = t0_rec = None
        next_clock = 0.0
        for m in messages:
            if m.key.endswith(CLOCK_KEY):
                self.clock = False   # the recording has the real clock: no synthetic one beside it
            if t0_wall is None:
                t0_wall, t0_rec = self.now(), m.log_time_ns
                next_clock = t0_wall
            due = t0_wall + (m.log_time_ns - t0_rec) * 1e-9 / self.rate
            while not self.stopped():
                now = self.now()
                if self.clock and next_clock <= now:
                    self._tick(t0_rec + int((now - t0_wall) * self.rate * 1e9))
                    next_clock += self.clock_period_s
                    continue
                if now >= due:
                    break
                self._wait((min(due, next_clock) if self.clock else due) - now)
            if self.stopped():
                break
            self.stats.late_max_s = max(self.stats.late_max_s, self.now() - due)
            self.publish(m.key, m.payload, m.encoding)
            self.stats.messages += 1
        return self.stats

    def _wait(self, dt: float) -> None:
        # time.sleep overshoots by ~0.1-1 ms (more under load): sleep most of it, spin the rest.
        if dt > self.spin_s:
            self.sleep(dt - self.spin_s / 2)
        else:
            end = self.now() + dt
            while self.now() < end:
                pass

    def _tick(self, stamp_ns: int) -> None:
        self.publish(self.clock_key, encode(Clock(header=Header(stamp_ns=stamp_ns), speed_factor=self.rate)), CLOCK_ENCODING)
        self.stats.clock_ticks += 1
