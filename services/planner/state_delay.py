"""How late a vehicle state reaches the planner, judged on one clock or across machines.

A backlog delivered after this process was stalled (SIGSTOP, swap) must not be planned from: it
would capture a hold point or a direction from the past and fly back to it. Lateness is judged
against the lowest delay seen (creeping up 1 ms a sample), so a constant clock offset between
machines is not mistaken for staleness. Plain arithmetic on nanosecond stamps: no clock read here.
"""
from __future__ import annotations

FLOOR_CREEP_NS = 1_000_000      # the lowest delay seen rises this much a sample (follows a slower link)
SAME_CLOCK_FLOOR_NS = 50_000_000  # a lowest delay under this is a latency: stamps and us share a clock


class StateDelay:
    """Per state: stale(now_ns, stamp_ns) to drop a backlog, age_s(...) for the trajectory tracker."""

    def __init__(self):
        self.floor_ns: int | None = None   # the lowest delay seen (None: no state yet, or a new source)
        self.stale_count = 0

    def reset(self) -> None:
        """Another source's stamps (the estimator was switched): start over."""
        self.floor_ns = None

    def stale(self, now_ns: int, stamp_ns: int, timeout_s: float) -> bool:
        """True (and counted) for a state later than timeout_s beyond the lowest delay seen."""
        delay = now_ns - stamp_ns
        self.floor_ns = delay if self.floor_ns is None else min(delay, self.floor_ns + FLOOR_CREEP_NS)
        if (delay - self.floor_ns) * 1e-9 > timeout_s:
            self.stale_count += 1
            return True
        return False

    def age_s(self, now_ns: int, stamp_ns: int, cap_s: float) -> float:
        """How old the state is: its delay on one clock; across machines (a lowest delay that is
        not a plausible latency: clock offset) only the delay above the lowest one seen. In
        0..cap_s."""
        delay = now_ns - stamp_ns
        floor = self.floor_ns or 0
        age_ns = delay if 0 <= floor < SAME_CLOCK_FLOOR_NS else delay - floor
        return min(max(0.0, age_ns * 1e-9), cap_s)
