"""Aggregation, free of Zenoh: inputs (with the monotonic time they arrived) in, Facts and a
SafetyStatus out. Freshness is judged here, so a silent input is never mistaken for a good one.

Conventions: every on_* method takes `now_s` (time.monotonic() in the service, any clock in
tests); battery is a 0..1 fraction; positions are ENU about the local origin (the geofence's
frame, the same one mission checks waypoints in).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from aeroperception.schemas import (
    BatteryState, DiagnosticStatus, GcsLink, Header, LandedState, PerceptionHealth, SafetyStatus, VehicleState,
    VehicleStatus,
)
from aeroperception.services.lib.geofence import Geofence
from aeroperception.services.runtime.config import param, section

from .rules import Battery, Facts, GeofenceAction, Verdict, evaluate


@dataclass(frozen=True)
class Config:
    """What the monitor judges by: contract.PARAMS of the same names (runtime/config.py builds it;
    defaults, units and ranges only there)."""

    required_services: tuple[str, ...] = param("required_services", lambda text: parse_services(text))
    battery_warn_fraction: float = param("battery_warn_fraction")
    battery_critical_fraction: float = param("battery_critical_fraction")
    battery_emergency_fraction: float = param("battery_emergency_fraction")
    geofence: Geofence = section(Geofence)
    geofence_warning_margin_m: float = param("geofence_warning_margin_m")
    geofence_action: GeofenceAction = param("geofence_action", GeofenceAction)
    state_timeout_s: float = param("state_timeout_s")
    battery_timeout_s: float = param("battery_timeout_s")
    gcs_timeout_s: float = param("gcs_timeout_s")
    perception_timeout_s: float = param("perception_timeout_s")
    diagnostics_timeout_s: float = param("diagnostics_timeout_s")


@dataclass(frozen=True)
class SafetyConfig:
    """The service's config: the monitor's, and the shell's timing (Service.CONFIG)."""

    monitor: Config = section(Config)
    estop_timeout_s: float = param("estop_timeout_s")
    check_rate_hz: float = param("check_rate_hz")
    status_rate_hz: float = param("status_rate_hz")


def parse_services(text: str) -> tuple[str, ...]:
    return tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))


def classify_battery(remaining: float | None, fc_warning: int, cfg: Config) -> Battery:
    """Worst of our thresholds on the charge and the flight controller's own warning."""
    ours = Battery.UNKNOWN
    if remaining is not None and math.isfinite(remaining):
        ours = (Battery.EMERGENCY if remaining < cfg.battery_emergency_fraction else
                Battery.CRITICAL if remaining < cfg.battery_critical_fraction else
                Battery.LOW if remaining < cfg.battery_warn_fraction else Battery.OK)
    fc = {BatteryState.WARNING_LOW: Battery.LOW, BatteryState.WARNING_CRITICAL: Battery.CRITICAL,
          BatteryState.WARNING_EMERGENCY: Battery.EMERGENCY,
          BatteryState.WARNING_FAILED: Battery.EMERGENCY}.get(fc_warning, Battery.UNKNOWN)
    return max(ours, fc)


def geofence_status(cfg: Config, distance_m: float | None) -> int:
    if distance_m is None:
        return SafetyStatus.GEOFENCE_OK
    if distance_m < 0:
        return SafetyStatus.GEOFENCE_VIOLATION
    if distance_m < cfg.geofence_warning_margin_m:
        return SafetyStatus.GEOFENCE_WARNING
    return SafetyStatus.GEOFENCE_OK


@dataclass
class _Service:
    alive: bool = False
    alive_since_s: float = 0.0
    diag: DiagnosticStatus | None = None
    diag_rx_s: float | None = None


class SafetyMonitor:
    """Latest inputs, judged at `now_s`; `status(now_s)` is the SafetyStatus to publish."""

    def __init__(self, config: Config):
        self.cfg = config
        self.services: dict[str, _Service] = {}
        self.state: VehicleState | None = None
        self.state_rx_s: float | None = None
        self.battery: BatteryState | None = None
        self.battery_rx_s: float | None = None
        self.vehicle_status: VehicleStatus | None = None
        self.vehicle_status_rx_s: float | None = None
        self.gcs: GcsLink | None = None
        self.gcs_rx_s: float | None = None
        self.gcs_ever_connected = False
        self.perception: PerceptionHealth | None = None
        self.perception_rx_s: float | None = None
        self.estop = ""
        self._estop_saw_disarmed = False
        self.verdict = Verdict()

    # ------------------------------------------------------------ inputs

    def on_liveliness(self, name: str, alive: bool, now_s: float) -> None:
        svc = self.services.setdefault(name, _Service())
        if alive and not svc.alive:
            # A new process: forget the old one's diagnostics (an ERROR of the dead one) and give
            # it diagnostics_timeout_s to report before it counts as hung.
            svc.alive_since_s, svc.diag, svc.diag_rx_s = now_s, None, None
        svc.alive = alive

    def on_diagnostics(self, msg: DiagnosticStatus, now_s: float) -> None:
        svc = self.services.setdefault(msg.name, _Service())
        svc.diag, svc.diag_rx_s = msg, now_s

    def on_vehicle_state(self, msg: VehicleState, now_s: float) -> None:
        self.state, self.state_rx_s = msg, now_s
        if self.estop:
            if not msg.armed:
                self._estop_saw_disarmed = True
            elif self._estop_saw_disarmed:   # armed again after the stop: a new flight
                self.estop, self._estop_saw_disarmed = "", False

    def on_battery(self, msg: BatteryState, now_s: float) -> None:
        self.battery, self.battery_rx_s = msg, now_s

    def on_vehicle_status(self, msg: VehicleStatus, now_s: float) -> None:
        self.vehicle_status, self.vehicle_status_rx_s = msg, now_s

    def on_gcs_link(self, msg: GcsLink, now_s: float) -> None:
        self.gcs, self.gcs_rx_s = msg, now_s
        self.gcs_ever_connected |= msg.connected

    def on_perception(self, msg: PerceptionHealth, now_s: float) -> None:
        self.perception, self.perception_rx_s = msg, now_s

    def on_emergency_stop(self, reason: str, executed: bool, message: str) -> None:
        """Latched until the vehicle is seen disarmed and then armed again (a new flight)."""
        self.estop = (f"emergency stop executed ({reason})" if executed
                      else f"emergency stop NOT executed ({reason}): {message}")
        self._estop_saw_disarmed = False

    # ------------------------------------------------------------ judgement

    @staticmethod
    def _fresh(rx_s: float | None, now_s: float, timeout_s: float) -> bool:
        return rx_s is not None and now_s - rx_s <= timeout_s

    def fc_connected(self, now_s: float) -> bool:
        return (self.state is not None and self.state.connected
                and self._fresh(self.state_rx_s, now_s, self.cfg.state_timeout_s))

    def service_problem(self, name: str, now_s: float) -> tuple[str, str]:
        """(kind, why) for service `name`: kind "" (fine), "dead" (no liveliness token), "hung"
        (alive but no diagnostics for diagnostics_timeout_s) or "error" (reports ERROR)."""
        svc = self.services.get(name)
        if svc is None or not svc.alive:
            return "dead", f"{name} not alive"
        silent_since = svc.diag_rx_s if svc.diag_rx_s is not None else svc.alive_since_s
        if now_s - silent_since > self.cfg.diagnostics_timeout_s:
            return "hung", f"{name} hung: no diagnostics for over {self.cfg.diagnostics_timeout_s:g} s"
        if svc.diag is not None and svc.diag.level == DiagnosticStatus.ERROR:
            return "error", f"{name} reports ERROR: {svc.diag.message}"
        return "", ""

    def dead_heartbeats(self, now_s: float) -> list[str]:
        """Required services without a heartbeat: token gone, or alive but silent (hung)."""
        return [n for n in self.cfg.required_services if self.service_problem(n, now_s)[0] in ("dead", "hung")]

    def battery_reading(self, now_s: float) -> tuple[float | None, float | None, int]:
        """(remaining 0..1, voltage, FC warning): fmu/out/battery_status when fresh, else state/vehicle."""
        if self.battery is not None and self._fresh(self.battery_rx_s, now_s, self.cfg.battery_timeout_s):
            b = self.battery
            return b.remaining_fraction, (b.voltage_v or None), b.warning
        if self.state is not None:
            return self.state.battery_remaining, self.state.battery_voltage_v, BatteryState.WARNING_NONE
        return None, None, BatteryState.WARNING_NONE

    def distance_to_geofence_m(self) -> float | None:
        if self.state is None:
            return None
        p = self.state.position_m
        d = self.cfg.geofence.distance_to_boundary_m(p.x, p.y, p.z)
        return d if math.isfinite(d) else None   # a non-finite position: unknown, not "inside"

    def airborne(self) -> bool:
        """Armed and not on the ground, from the last state known (kept when the link is lost)."""
        st = self.state
        return st is not None and st.armed and st.landed_state != LandedState.ON_GROUND

    def perception_problem(self, now_s: float) -> str:
        if self.perception is None:
            return ""  # optional input: unknown, not unhealthy
        if not self._fresh(self.perception_rx_s, now_s, self.cfg.perception_timeout_s):
            return f"perception/health silent for over {self.cfg.perception_timeout_s:g} s"
        if not self.perception.overall_healthy:
            vio = PerceptionHealth.status_name(self.perception.vio_status)
            return f"perception not healthy (VIO {vio}{': ' + self.perception.message if self.perception.message else ''})"
        return ""

    def gcs_connected(self, now_s: float) -> bool:
        return (self.gcs is not None and self.gcs.connected
                and self._fresh(self.gcs_rx_s, now_s, self.cfg.gcs_timeout_s))

    def fc_failsafe(self, now_s: float) -> str:
        vs = self.vehicle_status
        if vs is None or not vs.failsafe or not self._fresh(self.vehicle_status_rx_s, now_s, 2.0):
            return ""
        return vs.nav_state or "unknown mode"

    def facts(self, now_s: float) -> Facts:
        fmu_down = self.service_problem("fmu", now_s)[1] if "fmu" in self.cfg.required_services else ""
        others = tuple(why for kind, why in (self.service_problem(n, now_s) for n in self.cfg.required_services
                                             if n != "fmu") if kind)
        remaining, _volt, warning = self.battery_reading(now_s)
        distance = self.distance_to_geofence_m()
        return Facts(
            airborne=self.airborne(),
            fc_connected=self.fc_connected(now_s),
            fc_ever_connected=self.state is not None,
            fmu_down=fmu_down,
            services_down=others,
            battery=classify_battery(remaining, warning, self.cfg),
            battery_remaining=remaining,
            geofence_status=geofence_status(self.cfg, distance),
            distance_to_geofence_m=distance,
            geofence_action=self.cfg.geofence_action,
            gcs_lost=self.gcs_ever_connected and not self.gcs_connected(now_s),
            perception_problem=self.perception_problem(now_s),
            fc_failsafe=self.fc_failsafe(now_s),
            estop=self.estop,
        )

    def status(self, now_s: float, stamp_ns: int = 0) -> SafetyStatus:
        """Judge everything at `now_s`; the verdict is kept in `self.verdict`."""
        f = self.facts(now_s)
        self.verdict = v = evaluate(f)
        remaining, voltage, _ = self.battery_reading(now_s)
        dead = self.dead_heartbeats(now_s)
        fc = f.fc_connected
        battery_status = {Battery.LOW: SafetyStatus.BATTERY_WARNING, Battery.CRITICAL: SafetyStatus.BATTERY_CRITICAL,
                          Battery.EMERGENCY: SafetyStatus.BATTERY_CRITICAL}.get(f.battery, SafetyStatus.BATTERY_OK)
        return SafetyStatus(
            header=Header(stamp_ns=stamp_ns, frame_id="map"),
            safety_level=v.level,
            estimator_healthy=fc,
            controller_healthy=fc and not self.service_problem("fmu", now_s)[0],
            trajectory_healthy=not self.service_problem("planner", now_s)[0],
            px4_connected=fc,
            gcs_connected=self.gcs_connected(now_s),
            geofence_status=f.geofence_status,
            distance_to_geofence_m=f.distance_to_geofence_m,
            heartbeats_alive=len(self.cfg.required_services) - len(dead),
            heartbeats_total=len(self.cfg.required_services),
            dead_heartbeats=dead,
            battery_remaining=remaining,
            battery_voltage_v=voltage,
            battery_status=battery_status,
            active_warnings=list(v.warnings),
            active_errors=list(v.errors),
            recommended_action=v.action,
        )
