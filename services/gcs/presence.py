"""Whether a ground station is there (gcs/link), judged so that a false "lost" cannot pause a
mission (no Zenoh).

Three rules:
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


class Presence:
    """Which ground stations are alive and the verdict gcs/link publishes, with a log line for
    every station heard or lost and every change of the verdict.

    link: the UdpLink (its ground stations by heartbeat age, in ListeningClock time)."""

    def __init__(self, link, timeout_s: float, start_s: float, log):
        self.link = link
        self.timeout_s = timeout_s
        self.log = log
        self.verdict = LinkVerdict(timeout_s, start_s)
        self.alive: set[tuple[str, int]] = set()   # addresses of the ground stations alive
        self.last_heartbeat_s: float | None = None  # ListeningClock time of the last ground station heartbeat
        self.system_id = 0                          # the last ground station heard

    @property
    def connected(self) -> bool:
        return bool(self.verdict.connected)

    def heard(self, system_id: int, now_s: float) -> bool:
        """A ground station's heartbeat; True if the verdict changed (see update)."""
        self.last_heartbeat_s, self.system_id = now_s, system_id
        return self.update(now_s)

    def update(self, now_s: float) -> bool:
        """gcs/link is up while any ground station is alive (heartbeat within timeout_s of
        listening time); no verdict before a full timeout after start. True if the verdict
        changed (publish it at once)."""
        alive = {p.address for p in self.link.ground_stations(now_s)}
        for addr in sorted(self.alive - alive):
            self.log.warn("gcs_lost", address=f"{addr[0]}:{addr[1]}", timeout_s=self.timeout_s)
        for addr in sorted(alive - self.alive):
            peer = self.link.peers.get(addr)
            self.log.info("gcs_heard", address=f"{addr[0]}:{addr[1]}", system_id=peer.system_id if peer else None)
        self.alive = alive
        before = self.verdict.connected
        now_connected = self.verdict.update(now_s, bool(alive))
        if now_connected == before:
            return False
        if now_connected:
            self.log.info("gcs_link_up", system_id=self.system_id,
                          address=f"{self.link.remote[0]}:{self.link.remote[1]}")
        elif before:
            self.log.warn("gcs_link_lost", timeout_s=self.timeout_s)
        else:
            self.log.info("gcs_link_none", listened_s=self.timeout_s)
        return True

    def addresses(self) -> str:
        return ",".join(f"{a[0]}:{a[1]}" for a in sorted(self.alive))
