"""Process shell of the perception coordinator: health in, perception/health out (1 Hz + on change)."""
from __future__ import annotations

import time

from aeroperception.schemas import DiagnosticStatus, PerceptionHealth, VioHealth
from aeroperception.services.runtime import Health, ParamError, Service, run

from . import contract
from .logic import SOURCES, Coordinator, parse_sources

LEVEL = {PerceptionHealth.HEALTHY: DiagnosticStatus.OK, PerceptionHealth.NOT_CONFIGURED: DiagnosticStatus.OK,
         PerceptionHealth.FAILED: DiagnosticStatus.ERROR}


class PerceptionService(Service):
    """Perception coordinator (requirement PERC-1)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS

    def start(self) -> None:
        p = self.params
        self.coord = Coordinator({s: p[f"{s}_timeout_s"] for s in SOURCES}, parse_sources(p.sources))
        self.params.on_change(self._on_param)
        self.pub = self.node.publisher("perception/health", PerceptionHealth)
        self.last: PerceptionHealth | None = None
        self.last_sent_s = 0.0
        self.published = 0
        node = self.node
        node.subscribe("state/vio_health", VioHealth, lambda m: self._input(self.coord.on_vio, m))
        node.subscribe("perception/detector_health", DiagnosticStatus, lambda m: self._input(self.coord.on_detector, m))
        node.subscribe("diagnostics/lidar", DiagnosticStatus, lambda m: self._input(self.coord.on_lidar, m))
        self.loop = node.every(1.0 / p.check_rate_hz, self._check, name="check")

    def _on_param(self, name, value) -> None:
        if name.endswith("_timeout_s") and name[: -len("_timeout_s")] in SOURCES:
            self.coord.timeouts_s[name[: -len("_timeout_s")]] = value
        elif name == "check_rate_hz":
            self.loop.set_rate(value)
        elif name == "sources":
            try:
                self.coord.sources = parse_sources(value)
            except ValueError as e:
                raise ParamError(str(e)) from None
            self._check()

    def _input(self, feed, msg) -> None:
        feed(msg, time.monotonic())
        self._check()

    def _check(self) -> None:
        now = time.monotonic()
        msg = self.coord.verdict(now, self.node.now_ns())
        if self.coord.changed(msg) or now - self.last_sent_s >= 1.0 / self.params.publish_rate_hz:
            self.pub.publish(msg)
            self.last, self.last_sent_s = msg, now
            self.published += 1

    def health(self) -> Health:
        m = self.last
        if m is None:
            return Health(DiagnosticStatus.WARN, "no verdict yet", {})
        return Health(LEVEL.get(m.vio_status, DiagnosticStatus.WARN),
                      ("healthy: " if m.overall_healthy else "UNHEALTHY: ") + m.message,
                      {"overall_healthy": m.overall_healthy, "published": self.published,
                       **{f"{s}_status": PerceptionHealth.status_name(getattr(m, f"{s}_status")) for s in SOURCES}})


def main(argv=None) -> int:
    return run(PerceptionService, argv)
