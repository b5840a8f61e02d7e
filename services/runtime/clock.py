"""One clock for every service: wall time, or the simulator's `sim/clock` when running in sim.

Following sim/clock lets the whole stack run faster than real time and be replayed
deterministically. Between ticks the sim time is extrapolated with the announced speed factor
so stamps stay monotonic and smooth.
"""
from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .node import Node


class ServiceClock:
    """What a service stamps and sleeps by: wall time, or sim/clock followed (the message is
    schemas.Clock)."""

    def __init__(self, node: "Node | None" = None):
        self._lock = threading.Lock()
        self._sim_ns: int | None = None
        self._wall_at_tick = 0.0
        self._speed = 1.0
        self._last_ns = 0
        self.is_sim = node is not None
        if node is not None:
            from aeroperception.schemas import Clock as ClockMsg

            node.subscribe("sim/clock", ClockMsg, self._on_tick)

    def _on_tick(self, msg) -> None:
        with self._lock:
            self._sim_ns = msg.header.stamp_ns
            self._wall_at_tick = time.monotonic()
            self._speed = msg.speed_factor or 1.0

    def now_ns(self) -> int:
        if not self.is_sim:
            return time.time_ns()
        with self._lock:
            if self._sim_ns is None:
                return 0  # sim clock not heard yet: time has not started
            t = self._sim_ns + int((time.monotonic() - self._wall_at_tick) * self._speed * 1e9)
            self._last_ns = max(self._last_ns, t)
            return self._last_ns

    def sleep(self, duration_s: float) -> None:
        """Sleep `duration_s` of this clock's time (shorter in wall time when sim runs fast)."""
        time.sleep(duration_s / (self._speed if self.is_sim else 1.0))
