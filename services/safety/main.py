"""Process shell: inputs from Zenoh into the SafetyMonitor, safety/status out, the e-stop queryable."""
from __future__ import annotations

import time

from aeroperception.schemas import (
    BatteryState, DiagnosticStatus, EmergencyStopReply, EmergencyStopRequest, GcsLink, PerceptionHealth,
    SafetyStatus, VehicleState, VehicleStatus,
)
from aeroperception.services.lib.safety_names import ACTION_NAMES, LEVEL_NAMES
from aeroperception.services.runtime import CallError, Health, Service, run

from . import contract
from .monitor import SafetyConfig, SafetyMonitor


class SafetyService(Service):
    """SafetyStatus from liveliness, FC link, battery, geofence, GCS and perception (IF-2's SafetyStatus)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = SafetyConfig     # a bad polygon fails at start, and is refused live

    def start(self) -> None:
        self.monitor = SafetyMonitor(self.cfg.monitor)
        self.pub = self.io["safety/status"]
        self.last: SafetyStatus | None = None
        self.last_signature: tuple | None = None
        self.last_pub_s = 0.0
        self.counters = {"published": 0, "changes": 0, "estop_requests": 0, "estop_refused": 0}
        self.node.on_liveliness("*", lambda name, alive: self._judge(self.monitor.on_liveliness, name, alive,
                                                                     time.monotonic()))
        # state/vehicle (50 Hz) is only stored; the check loop judges it (a geofence crossing or a
        # stale link is seen within 1/check_rate_hz). Discrete events are judged at once.
        self.loop = self.node.every(1.0 / self.cfg.check_rate_hz, self._check, name="check")

    def on_config(self, cfg: SafetyConfig) -> None:
        if cfg.check_rate_hz != self.cfg.check_rate_hz:
            self.loop.set_rate(cfg.check_rate_hz)
        if cfg.monitor != self.cfg.monitor:
            self.monitor.cfg = cfg.monitor
            self._check()

    # ------------------------------------------------------------ inputs (contract.INPUTS)

    def on_state_vehicle(self, m: VehicleState) -> None:
        self.monitor.on_vehicle_state(m, time.monotonic())

    def on_fmu_out_vehicle_status(self, m: VehicleStatus) -> None:
        self.monitor.on_vehicle_status(m, time.monotonic())

    def on_fmu_out_battery_status(self, m: BatteryState) -> None:
        self._judge(self.monitor.on_battery, m, time.monotonic())

    def on_gcs_link(self, m: GcsLink) -> None:
        self._judge(self.monitor.on_gcs_link, m, time.monotonic())

    def on_perception_health(self, m: PerceptionHealth) -> None:
        self._judge(self.monitor.on_perception, m, time.monotonic())

    def on_diagnostics(self, m: DiagnosticStatus) -> None:
        self._judge(self.monitor.on_diagnostics, m, time.monotonic())

    def _judge(self, handler, *args) -> None:
        """A discrete event: taken, then judged at once."""
        handler(*args)
        self._check()

    def _check(self) -> None:
        """Judge now; publish at once when level, action, the matching rules or the dead
        heartbeats changed, else at status_rate_hz."""
        now = time.monotonic()
        status = self.monitor.status(now, self.node.now_ns())
        signature = (status.safety_level, status.recommended_action, self.monitor.verdict.rules,
                     tuple(status.dead_heartbeats), status.geofence_status, status.battery_status)
        changed = signature != self.last_signature
        if changed or now - self.last_pub_s >= 1.0 / self.cfg.status_rate_hz:
            if changed and self.last_signature is not None:
                self.counters["changes"] += 1
                self.log.info("safety_changed", safety_level=LEVEL_NAMES[status.safety_level],
                              action=ACTION_NAMES[status.recommended_action],
                              rules=list(self.monitor.verdict.rules), dead=status.dead_heartbeats,
                              errors=status.active_errors, warnings=status.active_warnings)
            self.pub.publish(status)
            self.counters["published"] += 1
            self.last_pub_s = now
        self.last, self.last_signature = status, signature

    def on_safety_emergency_stop(self, req: EmergencyStopRequest) -> EmergencyStopReply:
        """Operator's emergency stop: confirm + reason required; the FC's real outcome is the reply."""
        reason = req.reason.strip()
        with self.node.lock:
            self.counters["estop_requests"] += 1
            if not req.confirm or not reason:
                self.counters["estop_refused"] += 1
                why = "set confirm=true" if not req.confirm else "give a reason"
                self.log.warn("emergency_stop_refused", confirm=req.confirm, reason=reason)
                return EmergencyStopReply(success=False, message=f"refused: {why} to stop the motors (the vehicle falls)")
            self.log.error("emergency_stop", reason=reason)
        try:
            reply = self.node.call("fmu/srv/emergency_stop", EmergencyStopRequest(confirm=True, reason=reason),
                                   EmergencyStopReply, timeout_s=self.cfg.estop_timeout_s)
            executed, message = reply.success, reply.message
        except CallError as e:
            executed, message = False, str(e)
        with self.node.lock:
            self.monitor.on_emergency_stop(reason, executed, message)
            self.log.error("emergency_stop_result", executed=executed, message=message, reason=reason)
            self._check()
        return EmergencyStopReply(success=executed, message=("flight controller: " if executed else "not executed: ")
                                  + message)

    def health(self) -> Health:
        s = self.last
        if s is None:
            return Health(DiagnosticStatus.WARN, "starting")
        values = dict(self.counters, level=LEVEL_NAMES[s.safety_level], action=ACTION_NAMES[s.recommended_action],
                      rule=self.monitor.verdict.deciding_rule or "none",
                      heartbeats=f"{s.heartbeats_alive}/{s.heartbeats_total}",
                      dead=",".join(s.dead_heartbeats) or "none", warnings=len(s.active_warnings),
                      errors=len(s.active_errors), fc_connected=s.px4_connected,
                      distance_to_geofence_m=("n/a" if s.distance_to_geofence_m is None
                                              else round(s.distance_to_geofence_m, 1)))
        text = f"{LEVEL_NAMES[s.safety_level]}, recommends {ACTION_NAMES[s.recommended_action]}"
        if self.monitor.state is None:  # the service's own health: it cannot judge without the vehicle
            return Health(DiagnosticStatus.WARN, f"{text}; no state/vehicle received yet", values)
        return Health(DiagnosticStatus.OK, text, values)


def main(argv=None) -> int:
    return run(SafetyService, argv)
