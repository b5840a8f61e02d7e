"""Aggregation logic, free of Zenoh: feed statuses and liveliness, ask for the roll-up."""
from __future__ import annotations

from dataclasses import dataclass, field

from aeroperception.schemas import DiagnosticArray, DiagnosticStatus, Header
from aeroperception.services.runtime.config import param


@dataclass(frozen=True)
class DiagnosticsConfig:
    stale_after_s: float = param("stale_after_s")
    publish_rate_hz: float = param("publish_rate_hz")


@dataclass
class Aggregator:
    stale_after_s: float = 3.0
    latest: dict[str, tuple[float, DiagnosticStatus]] = field(default_factory=dict)
    alive: set[str] = field(default_factory=set)

    def on_status(self, status: DiagnosticStatus, now_s: float) -> None:
        self.latest[status.name] = (now_s, status)

    def on_liveliness(self, service: str, alive: bool) -> None:
        (self.alive.add if alive else self.alive.discard)(service)

    def rollup(self, now_s: float, stamp_ns: int) -> DiagnosticArray:
        out = []
        for name in sorted(set(self.latest) | self.alive):
            seen_s, st = self.latest.get(name, (None, None))
            if st is None:
                out.append(DiagnosticStatus(name=name, level=DiagnosticStatus.STALE,
                                            message="alive but no diagnostics received yet"))
            elif now_s - seen_s > self.stale_after_s or (self.alive and name not in self.alive):
                why = "not alive" if name not in self.alive else f"silent for {now_s - seen_s:.1f} s"
                out.append(DiagnosticStatus(header=st.header, name=name, level=DiagnosticStatus.STALE,
                                            message=f"STALE ({why}); last: {st.message}",
                                            hardware_id=st.hardware_id, values=st.values))
            else:
                out.append(st)
        return DiagnosticArray(header=Header(stamp_ns=stamp_ns), status=out)

    @staticmethod
    def worst(arr: DiagnosticArray) -> int:
        return max((s.level for s in arr.status), default=DiagnosticStatus.OK)
