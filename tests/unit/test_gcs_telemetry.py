"""Telemetry to ground stations: NED and geodetic about home, message intervals, the geofence in
SYS_STATUS, the onboard-computer identity."""
from __future__ import annotations

import math

import pytest
from gcs_support import HOME
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import Quaternion, Vector3, VehicleState
from aeroperception.services.gcs.telemetry import CAPABILITIES, Scheduler, TelemetryState
from aeroperception.services.mavlink import px4


def test_telemetry_is_ned_and_geodetic_about_home():
    st = VehicleState(position_m=Vector3(x=10.0, y=20.0, z=5.0), velocity_mps=Vector3(x=1.0, y=0.0, z=0.5),
                      orientation=Quaternion.from_yaw(0.0), yaw_rad=0.0, armed=True, flight_mode="OFFBOARD",
                      landed_state=2, battery_voltage_v=15.2, battery_remaining=0.8, connected=True)
    tel = TelemetryState(HOME, vehicle=st)
    lp = tel.local_position_ned()
    assert (lp.x, lp.y, lp.z, lp.vx, lp.vz) == pytest.approx((20.0, 10.0, -5.0, 0.0, -0.5))
    att = tel.attitude()
    assert att.yaw == pytest.approx(math.pi / 2) and att.roll == pytest.approx(0.0, abs=1e-9)
    gp = tel.global_position_int()
    north, east = HOME.projection.project(gp.lat / 1e7, gp.lon / 1e7)
    assert (north, east) == pytest.approx((20.0, 10.0), abs=0.02)
    assert gp.relative_alt == 5000 and gp.alt == 15000 and gp.hdg == 9000
    hb = tel.heartbeat()
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and px4.decode(hb.custom_mode) == "OFFBOARD"
    ss = tel.sys_status()
    assert ss.voltage_battery == 15200 and ss.battery_remaining == 80
    assert tel.extended_sys_state().landed_state == 2
    assert tel.autopilot_version().capabilities == CAPABILITIES
    assert CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT and CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    # ground-station setpoints are ignored, so not advertised
    assert not CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    hp = tel.home_position()
    assert hp.latitude == int(round(HOME.lat_deg * 1e7))


def test_scheduler_intervals():
    tel = TelemetryState(HOME)
    s = Scheduler(0.9, tel.build)
    first = {m.get_type() for m in s.due(0.0)}
    assert {"HEARTBEAT", "SYS_STATUS", "GLOBAL_POSITION_INT", "HOME_POSITION"} <= first
    assert s.due(0.5) == []
    assert s.set_interval(M.MAVLINK_MSG_ID_ATTITUDE, 100_000)
    assert [m.get_type() for m in s.due(0.6)] == ["ATTITUDE"]
    assert s.set_interval(M.MAVLINK_MSG_ID_ATTITUDE, -1)
    assert "ATTITUDE" not in {m.get_type() for m in s.due(5.0)}
    assert not s.set_interval(9999, 1000)


def test_companion_identity_heartbeat_is_an_onboard_computer():
    """In the vehicle profile gcs is not a second vehicle."""
    hb = TelemetryState(HOME, companion=True).heartbeat()
    assert (hb.type, hb.autopilot, hb.base_mode, hb.custom_mode) == (M.MAV_TYPE_ONBOARD_CONTROLLER,
                                                                     M.MAV_AUTOPILOT_INVALID, 0, 0)
    hb = TelemetryState(HOME).heartbeat()
    assert (hb.type, hb.autopilot) == (M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4)
