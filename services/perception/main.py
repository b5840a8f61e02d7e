"""Process shell of the perception coordinator: health in, perception/health out (1 Hz + on change)."""
from __future__ import annotations

import time

from aeroperception.schemas import DiagnosticStatus, PerceptionHealth, VioHealth
from aeroperception.services.runtime import Health, ParamError, Service, run

from . import contract
from .logic import SOURCES, Coordinator, CoordinatorConfig

LEVEL = {PerceptionHealth.HEALTHY: DiagnosticStatus.OK, PerceptionHealth.NOT_CONFIGURED: DiagnosticStatus.OK,
         PerceptionHealth.FAILED: DiagnosticStatus.ERROR}


class PerceptionService(Service):
    """Perception coordinator (requirement PERC-1)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = CoordinatorConfig

    def start(self) -> None:
        self.coord = Coordinator.from_config(self.cfg)
        self.pub = self.io["perception/health"]
        self.last: PerceptionHealth | None = None
        self.last_sent_s = 0.0
        self.published = 0
        self.loop = self.node.every(1.0 / self.cfg.check_rate_hz, self._check, name="check")

    def on_config(self, cfg: CoordinatorConfig) -> None:
        try:
            self.coord.configure(cfg)
        except ValueError as e:
            raise ParamError(str(e)) from None
        if cfg.check_rate_hz != self.cfg.check_rate_hz:
            self.loop.set_rate(cfg.check_rate_hz)
        if cfg.sources != self.cfg.sources:
            self._check(cfg)

    def on_state_vio_health(self, msg: VioHealth) -> None:
        self.coord.on_vio(msg, time.monotonic())
        self._check()

    def on_perception_detector_health(self, msg: DiagnosticStatus) -> None:
        self.coord.on_detector(msg, time.monotonic())
        self._check()

    def on_diagnostics_lidar(self, msg: DiagnosticStatus) -> None:
        self.coord.on_lidar(msg, time.monotonic())
        self._check()

    def _check(self, cfg: CoordinatorConfig | None = None) -> None:
        """The verdict, published on a change or when due (`cfg`: the one about to be taken)."""
        now = time.monotonic()
        msg = self.coord.verdict(now, self.node.now_ns())
        if self.coord.changed(msg) or now - self.last_sent_s >= 1.0 / (cfg or self.cfg).publish_rate_hz:
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
