"""Whether a ground station is there (gcs/link), judged so that a false "lost" cannot pause a
mission (no Zenoh).

Three rules (issue 8 #4):
- Only ground stations count: a HEARTBEAT with MAV_TYPE_GCS, or from a system id listed in the
  `gcs_system_ids` parameter (`GroundStationFilter`). A stray heartbeat of another type never
  makes the link "up", so its silence never makes it "lost".
- No verdict before a full `gcs_timeout_s` of listening after start (`LinkVerdict`): a restarted
  gcs says nothing on gcs/link until it has either heard a ground station (up) or listened for
  the whole timeout without one (down). The mission service reacts to changes only, so a restart
  next to a connected ground station is not a loss.
- Time we could not listen does not count (`ListeningClock`): a heartbeat's age is measured in
  time during which gcs was running. A process stopped for 15 s (SIGSTOP, or starved) cannot
  receive; when it resumes, the heartbeats queued in the socket during the stall are read
  within milliseconds and the link stays up. If the ground station really went away during the
  stall, the loss is declared after `gcs_timeout_s` of listening after the resume, from the
  arrival times of the packets actually received, never from wall time that passed while stopped.
"""
from __future__ import annotations

import time
from typing import Callable, Iterable

from pymavlink.dialects.v20 import common as M

STALL_S = 1.0   # a gap this long between two ticks (ticks every 0.05 s) is a stall, not listening


class ListeningClock:
    """Monotonic seconds that stop while the process is not running.

    `tick()` is called by a periodic timer; a gap of more than `stall_s` between two ticks is a
    stall and everything beyond `stall_s` of it is taken out. Between ticks the clock never runs
    more than `stall_s` past the last tick, so a packet read right after a resume, before the
    timer has noticed the stall, is not stamped "in the future"."""

    def __init__(self, stall_s: float = STALL_S, source: Callable[[], float] = time.monotonic):
        self.stall_s = stall_s
        self.source = source
        self.stalled_s = 0.0        # time taken out so far
        self.stalls = 0
        self.last_tick: float | None = None

    def tick(self) -> float:
        """Note that the process runs; returns the stall just detected (s, 0 if none)."""
        raw = self.source()
        stall = 0.0
        if self.last_tick is not None and raw - self.last_tick > self.stall_s:
            stall = raw - self.last_tick - self.stall_s
            self.stalled_s += stall
            self.stalls += 1
        self.last_tick = raw
        return stall

    def __call__(self) -> float:
        raw = self.source()
        if self.last_tick is not None:
            raw = min(raw, self.last_tick + self.stall_s)
        return raw - self.stalled_s


class GroundStationFilter:
    """Is this HEARTBEAT from a ground station? MAV_TYPE_GCS, or a configured system id."""

    def __init__(self, system_ids: Iterable[int] = ()):
        self.system_ids = frozenset(int(s) for s in system_ids)

    @classmethod
    def from_param(cls, text: str) -> "GroundStationFilter":
        """"255, 254" -> ids; ValueError naming the bad entry."""
        ids = []
        for part in str(text).replace(";", ",").split(","):
            part = part.strip()
            if not part:
                continue
            if not part.isdigit() or not 1 <= int(part) <= 255:
                raise ValueError(f"gcs_system_ids: {part!r} is not a MAVLink system id (1-255)")
            ids.append(int(part))
        return cls(ids)

    def __call__(self, msg) -> bool:
        return msg.type == M.MAV_TYPE_GCS or msg.get_srcSystem() in self.system_ids


class LinkVerdict:
    """gcs/link's `connected`: None (no verdict yet), True or False.

    update(now, alive) with `alive` = some ground station's heartbeat within the timeout (in
    ListeningClock time). Before any ground station is heard, the verdict stays None until
    `timeout_s` of listening has passed since `start_s`."""

    def __init__(self, timeout_s: float, start_s: float):
        self.timeout_s = timeout_s
        self.start_s = start_s
        self.connected: bool | None = None

    def update(self, now_s: float, alive: bool) -> bool | None:
        if alive:
            self.connected = True
        elif self.connected or now_s - self.start_s >= self.timeout_s:
            self.connected = False
        return self.connected
