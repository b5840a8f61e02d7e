"""Process shell: wires the Aggregator to Zenoh."""
from __future__ import annotations

import time

from aeroperception.schemas import DiagnosticStatus
from aeroperception.services.runtime import Health, Service, run

from . import contract
from .logic import Aggregator


class DiagnosticsService(Service):
    """Aggregate every service's health into diagnostics/agg."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS

    def start(self) -> None:
        self.agg = Aggregator(stale_after_s=self.params.stale_after_s)
        self.params.on_change(lambda n, v: setattr(self.agg, "stale_after_s", v) if n == "stale_after_s" else None)
        self.node.subscribe("diagnostics/*", DiagnosticStatus, self._on_status)
        self.node.on_liveliness("*", self.agg.on_liveliness)
        self.pub = self.node.publisher("diagnostics/agg", contract.OUTPUTS["diagnostics/agg"])
        self.last = None
        self.loop = self.node.every(1.0 / self.params.publish_rate_hz, self._publish, name="publish")
        self.params.on_change(lambda n, v: self.loop.set_rate(v) if n == "publish_rate_hz" else None)

    def _on_status(self, st: DiagnosticStatus) -> None:
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
