"""safety/status to ground stations: the geofence bits of SYS_STATUS and a STATUSTEXT once per
change."""
from __future__ import annotations

import time

from gcs_support import HOME
from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.telemetry import TelemetryState


def test_safety_status_fence_bits_and_statustext_once_per_change():
    """No safety/status -> no fence in SYS_STATUS; then present/enabled/healthy from
    geofence_status; warnings and errors -> STATUSTEXT once when they appear, INFO when cleared."""
    from aeroperception.schemas import SafetyStatus
    from aeroperception.services.gcs.safety_relay import SafetyRelay
    fence = M.MAV_SYS_STATUS_GEOFENCE
    tel = TelemetryState(HOME)
    s = tel.sys_status()
    assert not (s.onboard_control_sensors_present | s.onboard_control_sensors_enabled) & fence
    tel.safety, tel.safety_rx_s = SafetyStatus(distance_to_geofence_m=50.0), time.monotonic()
    s = tel.sys_status()
    assert s.onboard_control_sensors_present & s.onboard_control_sensors_enabled & s.onboard_control_sensors_health & fence
    tel.safety = SafetyStatus(geofence_status=SafetyStatus.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0)
    assert tel.fence_bits() == (fence, fence, 0)                      # breached: present, enabled, unhealthy
    tel.safety = SafetyStatus(distance_to_geofence_m=None)
    assert tel.fence_bits() == (fence, 0, fence)                      # safety runs without a fence
    assert tel.fence_bits(now_s=tel.safety_rx_s + 10.0) == (0, 0, 0)  # safety gone quiet: unknown

    relay = SafetyRelay()
    st = SafetyStatus(active_warnings=["battery low"], active_errors=["fmu dead"])
    assert relay.update(st) == [(M.MAV_SEVERITY_CRITICAL, "Safety: fmu dead"), (M.MAV_SEVERITY_WARNING, "Safety: battery low")]
    assert relay.update(st) == []                                      # repeated at 1 Hz: once only
    st = SafetyStatus(active_warnings=["battery low"], active_errors=["fmu dead", "geofence breached"],
                      safety_level=SafetyStatus.LEVEL_EMERGENCY)
    assert relay.update(st) == [(M.MAV_SEVERITY_EMERGENCY, "Safety: geofence breached")]
    assert relay.update(SafetyStatus()) == [(M.MAV_SEVERITY_INFO, "Safety: cleared: battery low"),
                                            (M.MAV_SEVERITY_INFO, "Safety: cleared: fmu dead"),
                                            (M.MAV_SEVERITY_INFO, "Safety: cleared: geofence breached")]
