"""GPS_RAW_INT and ESTIMATOR_STATUS from the flight controller to the ground station, without
sockets: the built-in sim's messages (packed and parsed as on the wire) -> fmu's conversion ->
gcs's telemetry. gcs used to report a 3D RTK fix with 16 satellites whatever the FC said, also
in GPS-denied flight; now it says what the FC says, and NO_GPS when it says nothing.
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import EstimatorStatus, GpsPosition
from aeroperception.services.fmu.navigation import estimator_status_from_mavlink, gps_from_mavlink
from aeroperception.services.gcs.home import Home
from aeroperception.services.gcs.telemetry import DEFAULT_STREAM, FC_STATUS_STALE_S, ID, TelemetryState
from aeroperception.services.sim.vehicle.mavlink_module import MavlinkModule
from aeroperception.services.sim.vehicle.model import SimVehicle

WIRE = M.MAVLink(None, srcSystem=1, srcComponent=1)


def on_the_wire(msg):
    """The message as a receiver parses it (extension fields, NaN and sentinels included)."""
    parser = M.MAVLink(None)
    return parser.decode(bytearray(msg.pack(WIRE)))


def sim(**params) -> MavlinkModule:
    v = SimVehicle(params, seed=2)
    v.run_for(0.5)
    return MavlinkModule(v)


def gcs_with(gps: GpsPosition | None = None, est: EstimatorStatus | None = None, age_s: float = 0.0):
    tel = TelemetryState(Home(47.397742, 8.545594, 488.0))
    now = time.monotonic()
    tel.gps, tel.gps_rx_s = gps, now - age_s
    tel.estimator, tel.estimator_rx_s = est, now - age_s
    return tel


def test_with_gps_the_ground_station_sees_the_fcs_3d_fix():
    fc = sim()
    sent = on_the_wire(fc.streams.gps_raw_int())
    gps = gps_from_mavlink(sent, 1)
    assert gps.fix_type == GpsPosition.FIX_3D and gps.satellites_visible == 12
    home = fc.vehicle.params
    assert gps.latitude_deg == pytest.approx(home.SIM_HOME_LAT, abs=1e-6)
    assert gps.longitude_deg == pytest.approx(home.SIM_HOME_LON, abs=1e-6)
    assert gps.hdop == pytest.approx(0.8) and gps.horizontal_accuracy_m == pytest.approx(0.01)
    raw = on_the_wire(gcs_with(gps).gps_raw_int())
    assert (raw.fix_type, raw.satellites_visible, raw.lat, raw.lon, raw.alt, raw.eph, raw.epv, raw.h_acc) == \
        (sent.fix_type, sent.satellites_visible, sent.lat, sent.lon, sent.alt, sent.eph, sent.epv, sent.h_acc)


def test_gps_denied_the_ground_station_sees_no_fix_and_no_satellites():
    fc = sim(SIM_GPS_DENIED=True)
    gps = gps_from_mavlink(on_the_wire(fc.streams.gps_raw_int()), 1)
    assert gps.fix_type == GpsPosition.FIX_NO_FIX and gps.satellites_visible == 0
    assert gps.latitude_deg is None and gps.hdop is None and gps.ground_speed_mps is None
    raw = on_the_wire(gcs_with(gps).gps_raw_int())
    assert raw.fix_type == M.GPS_FIX_TYPE_NO_FIX and raw.satellites_visible == 0
    assert (raw.lat, raw.lon, raw.eph, raw.epv, raw.vel, raw.cog) == (0, 0, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF)


@pytest.mark.parametrize("age_s", [None, FC_STATUS_STALE_S + 1.0])
def test_without_a_fresh_report_from_the_fc_gcs_says_no_gps(age_s):
    gps = None if age_s is None else GpsPosition(fix_type=GpsPosition.FIX_3D, latitude_deg=47.0, longitude_deg=8.0,
                                                  altitude_amsl_m=500.0, satellites_visible=10)
    tel = gcs_with(gps, age_s=age_s or 0.0)
    raw = on_the_wire(tel.gps_raw_int())
    assert raw.fix_type == M.GPS_FIX_TYPE_NO_GPS and raw.satellites_visible == 255 and (raw.lat, raw.lon) == (0, 0)
    assert tel.estimator_status() is None     # no estimator status invented either


def fused_vision(fc: MavlinkModule) -> None:
    v = fc.vehicle
    for _ in range(10):
        v.run_for(0.05)
        v.estimator.on_vision(v.time_ns, v.time_ns, v.state.position_enu_m, np.array([1.0, 0, 0, 0]))
    assert v.estimator.valid(v.time_ns)


@pytest.mark.parametrize(("params", "vision", "abs_pos", "rel_pos", "const_pos"), [
    ({}, False, True, True, False),                        # GPS: absolute horizontal position
    ({"SIM_GPS_DENIED": True}, True, False, True, False),  # vision only: relative, never absolute
    ({"SIM_GPS_DENIED": True}, False, False, False, True), # no aiding yet: no position at all
])
def test_estimator_status_says_where_the_position_comes_from(params, vision, abs_pos, rel_pos, const_pos):
    fc = sim(**params)
    if vision:
        fused_vision(fc)
    sent = on_the_wire(fc.streams.estimator_status())
    est = estimator_status_from_mavlink(sent, 1)
    assert bool(est.flags & EstimatorStatus.POS_HORIZ_ABS) is abs_pos
    assert bool(est.flags & EstimatorStatus.POS_HORIZ_REL) is rel_pos
    assert bool(est.flags & EstimatorStatus.CONST_POS_MODE) is const_pos
    assert est.flags & EstimatorStatus.ATTITUDE and est.velocity_test_ratio is None   # NaN on the wire
    out = on_the_wire(gcs_with(est=est).estimator_status())
    assert out.flags == sent.flags
    assert out.pos_horiz_accuracy == pytest.approx(sent.pos_horiz_accuracy) and math.isnan(out.vel_ratio)


def test_gps_and_estimator_status_are_in_the_fcs_and_gcss_default_streams():
    fc = sim()
    rates = fc.streams.stream_rates_hz()
    assert rates["GPS_RAW_INT"] > 0 and rates["ESTIMATOR_STATUS"] > 0
    assert "GPS_RAW_INT" in DEFAULT_STREAM and "ESTIMATOR_STATUS" in DEFAULT_STREAM
    assert ID["ESTIMATOR_STATUS"] == M.MAVLINK_MSG_ID_ESTIMATOR_STATUS


def test_course_over_ground_is_enu_on_zenoh_and_ned_on_mavlink():
    m = M.MAVLink_gps_raw_int_message(0, 3, 0, 0, 0, 80, 120, 250, 9000, 10)   # 2.5 m/s towards East
    gps = gps_from_mavlink(m, 1)
    assert gps.course_rad == pytest.approx(0.0, abs=1e-9) and gps.ground_speed_mps == pytest.approx(2.5)
    raw = on_the_wire(gcs_with(gps).gps_raw_int())
    assert raw.cog == 9000 and raw.vel == 250
