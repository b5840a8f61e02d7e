"""The coordinator's verdict, free of Zenoh: statuses in (with the time they came), PerceptionHealth out.

Mapping (requirement PERC-1, PerceptionHealth's enum): VIO INIT -> INITIALIZING, TRACKING -> HEALTHY,
DEGRADED -> DEGRADED, LOST -> FAILED; a DiagnosticStatus OK -> HEALTHY, WARN -> DEGRADED,
ERROR -> FAILED, STALE -> UNKNOWN; a source silent past its timeout (or never heard) is UNKNOWN; a
source the stack does not run (not in `sources`: no camera, no LiDAR) is NOT_CONFIGURED, not broken.
overall_healthy iff VIO is HEALTHY: only the VIO gates flight (the detector and LiDAR are reported);
a stack without VIO has nothing to gate on and is healthy.
"""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.schemas import DiagnosticStatus, Header, PerceptionHealth, VioHealth
from aeroperception.services.runtime import param

PH = PerceptionHealth
VIO_STATUS = {VioHealth.INIT: PH.INITIALIZING, VioHealth.TRACKING: PH.HEALTHY,
              VioHealth.DEGRADED: PH.DEGRADED, VioHealth.LOST: PH.FAILED}
DIAG_STATUS = {DiagnosticStatus.OK: PH.HEALTHY, DiagnosticStatus.WARN: PH.DEGRADED,
               DiagnosticStatus.ERROR: PH.FAILED, DiagnosticStatus.STALE: PH.UNKNOWN}
SOURCES = ("vio", "detector", "lidar")
QUIET = (PH.HEALTHY, PH.NOT_CONFIGURED)   # statuses the verdict's message gives without detail


@dataclass(frozen=True)
class CoordinatorConfig:
    """The coordinator's parameters (contract.PARAMS), rebuilt on a live change."""

    sources: str = param("sources")
    vio_timeout_s: float = param("vio_timeout_s")
    detector_timeout_s: float = param("detector_timeout_s")
    lidar_timeout_s: float = param("lidar_timeout_s")
    publish_rate_hz: float = param("publish_rate_hz")
    check_rate_hz: float = param("check_rate_hz")

    def timeouts_s(self) -> dict[str, float]:
        return {"vio": self.vio_timeout_s, "detector": self.detector_timeout_s, "lidar": self.lidar_timeout_s}


@dataclass
class _Seen:
    status: int = PH.UNKNOWN
    detail: str = ""
    at_s: float | None = None


def parse_sources(text: str) -> frozenset[str]:
    """`sources` ("vio,detector"; "" = none) -> the set; ValueError naming an unknown one."""
    names = frozenset(s.strip() for s in text.split(",") if s.strip())
    unknown = sorted(names - set(SOURCES))
    if unknown:
        raise ValueError(f"sources: unknown {', '.join(unknown)}; known: {', '.join(SOURCES)}")
    return names


class Coordinator:
    def __init__(self, timeouts_s: dict[str, float], sources: frozenset[str] = frozenset(SOURCES)):
        self.timeouts_s = dict(timeouts_s)
        self.sources = sources
        self.seen = {s: _Seen() for s in SOURCES}
        self.last_key: tuple | None = None

    @classmethod
    def from_config(cls, cfg: CoordinatorConfig) -> "Coordinator":
        return cls(cfg.timeouts_s(), parse_sources(cfg.sources))

    def configure(self, cfg: CoordinatorConfig) -> None:
        """A new config (a live change); ValueError naming an unknown source, nothing changed."""
        sources = parse_sources(cfg.sources)
        self.timeouts_s, self.sources = cfg.timeouts_s(), sources

    def on_vio(self, msg: VioHealth, now_s: float) -> None:
        self.seen["vio"] = _Seen(VIO_STATUS.get(msg.state, PH.UNKNOWN), f"{msg.state_name}: {msg.message}", now_s)

    def on_detector(self, msg: DiagnosticStatus, now_s: float) -> None:
        self.seen["detector"] = _Seen(DIAG_STATUS.get(msg.level, PH.UNKNOWN), msg.message, now_s)

    def on_lidar(self, msg: DiagnosticStatus, now_s: float) -> None:
        self.seen["lidar"] = _Seen(DIAG_STATUS.get(msg.level, PH.UNKNOWN), msg.message, now_s)

    def status(self, source: str, now_s: float) -> tuple[int, str]:
        if source not in self.sources:
            return PH.NOT_CONFIGURED, "not in this stack"
        s = self.seen[source]
        if s.at_s is None:
            return PH.UNKNOWN, "no status yet"
        if now_s - s.at_s > self.timeouts_s[source]:
            return PH.UNKNOWN, f"silent for {now_s - s.at_s:.1f} s"
        return s.status, s.detail

    def verdict(self, now_s: float, stamp_ns: int) -> PerceptionHealth:
        st = {src: self.status(src, now_s) for src in SOURCES}
        healthy = st["vio"][0] in (PH.HEALTHY, PH.NOT_CONFIGURED)
        parts = [f"{src} {PH.status_name(code)}" + (f" ({detail[:80]})" if detail and code not in QUIET else "")
                 for src, (code, detail) in st.items()]
        return PerceptionHealth(header=Header(stamp_ns=stamp_ns), vio_status=st["vio"][0],
                                detector_status=st["detector"][0], lidar_status=st["lidar"][0],
                                overall_healthy=healthy, message="; ".join(parts))

    def changed(self, msg: PerceptionHealth) -> bool:
        """Whether any status differs from the last verdict passed here (the on-change trigger)."""
        key = (msg.vio_status, msg.detector_status, msg.lidar_status, msg.overall_healthy)
        changed, self.last_key = key != self.last_key, key
        return changed
