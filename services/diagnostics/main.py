"""Process shell: wires the Aggregator to Zenoh."""
from __future__ import annotations

import time

from aeroperception.schemas import DiagnosticStatus
from aeroperception.services.runtime import Health, Service, run

from . import contract
from .logic import Aggregator, DiagnosticsConfig


class DiagnosticsService(Service):
    """Aggregate every service's health into diagnostics/agg."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = DiagnosticsConfig

    def start(self) -> None:
        self.agg = Aggregator(stale_after_s=self.cfg.stale_after_s)
        self.node.on_liveliness("*", self.agg.on_liveliness)
        self.pub = self.io["diagnostics/agg"]
        self.last = None
        self.loop = self.node.every(1.0 / self.cfg.publish_rate_hz, self._publish, name="publish")

    def on_config(self, cfg: DiagnosticsConfig) -> None:
        self.agg.stale_after_s = cfg.stale_after_s
        if cfg.publish_rate_hz != self.cfg.publish_rate_hz:
            self.loop.set_rate(cfg.publish_rate_hz)

    def on_diagnostics(self, st: DiagnosticStatus) -> None:
        self.agg.on_status(st, time.monotonic())

    def _publish(self) -> None:
        self.last = self.agg.rollup(time.monotonic(), self.node.now_ns())
        self.pub.publish(self.last)

    def health(self) -> Health:
        n = len(self.last.status) if self.last else 0
        stale = [s.name for s in self.last.status if s.level == DiagnosticStatus.STALE] if self.last else []
        return Health(DiagnosticStatus.OK, f"aggregating {n} services",
                      {"services": n, "stale": ",".join(stale) or "none",
                       "worst_level": Aggregator.worst(self.last) if self.last else 0})


def main(argv=None) -> int:
    return run(DiagnosticsService, argv)
