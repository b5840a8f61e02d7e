"""A ground station (pymavlink on gcs's UDP endpoint) sees the flight controller's real GPS and
estimator state: a 3D fix and an absolute position with GPS; no fix, no satellites and a position
relative only (from vision) in `aero up --gps-denied`. gcs used to report a 3D RTK fix with 16
satellites in both. Truth: the sim's own diagnostics (gps_denied, position_valid)."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aeroperception.schemas import DiagnosticStatus, EstimatorStatus, GpsPosition  # noqa: E402
from aeroperception.services.sim.vehicle.params import make_params  # noqa: E402
from aerotest import free_udp_port, wait_for_message  # noqa: E402
from test_gcs import Gcs  # noqa: E402

SIM = make_params()
REL, ABS = M.ESTIMATOR_POS_HORIZ_REL, M.ESTIMATOR_POS_HORIZ_ABS


def gcs_stack(stack, gcs_port: int, extra: list[str], services: list[str], timeout_s: float):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    return stack(services, extra_args=[
        *extra, "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
        "--arg", f"gcs:--local-port={gcs_port}", "--arg", f"gcs:--remote-port={free_udp_port()}",
        "--arg", "gcs:--bind-ip=127.0.0.1"], timeout_s=timeout_s)


def sim_says(st, name: str, value: str, timeout_s: float) -> None:
    wait_for_message(st.session, "diagnostics/sim", DiagnosticStatus,
                     lambda d: str(d.values.get(name)) == value, timeout_s=timeout_s)


def test_with_gps_the_ground_station_sees_a_3d_fix_and_an_absolute_position(stack):
    port = free_udp_port()
    st = gcs_stack(stack, port, ["--sensors", "none"], ["sim", "fmu", "gcs"], 40)
    g = Gcs(port)
    try:
        sim_says(st, "gps_denied", "False", 10)
        gps = wait_for_message(st.session, "fmu/out/vehicle_gps_position", GpsPosition, timeout_s=10)
        assert gps.fix_type == GpsPosition.FIX_3D and gps.satellites_visible == 12
        raw = g.recv("GPS_RAW_INT", lambda m: m.fix_type != M.GPS_FIX_TYPE_NO_GPS, timeout_s=10)
        assert raw.fix_type == M.GPS_FIX_TYPE_3D_FIX and raw.satellites_visible == 12
        assert abs(raw.lat / 1e7 - SIM.SIM_HOME_LAT) < 1e-5 and abs(raw.lon / 1e7 - SIM.SIM_HOME_LON) < 1e-5
        assert abs(raw.alt / 1e3 - SIM.SIM_HOME_ALT) < 0.5 and raw.eph == 80
        est = g.recv("ESTIMATOR_STATUS", timeout_s=10)
        assert est.flags & ABS and est.flags & REL and not est.flags & M.ESTIMATOR_CONST_POS_MODE
        assert wait_for_message(st.session, "fmu/out/estimator_status", EstimatorStatus).flags == est.flags
    finally:
        g.close()


@pytest.mark.timeout(300)
def test_gps_denied_the_ground_station_sees_no_fix_and_a_position_from_vision(stack):
    port = free_udp_port()
    st = gcs_stack(stack, port, ["--gps-denied", "--scenario", "village", "--sensors", "camera", "--speed", "0.5"],
                   ["sim", "fmu", "vio", "perception", "gcs"], 60)
    g = Gcs(port)
    try:
        sim_says(st, "gps_denied", "True", 10)
        raw = g.recv("GPS_RAW_INT", lambda m: m.fix_type != M.GPS_FIX_TYPE_NO_GPS, timeout_s=15)
        assert raw.fix_type == M.GPS_FIX_TYPE_NO_FIX and raw.satellites_visible == 0
        assert (raw.lat, raw.lon, raw.eph) == (0, 0, 0xFFFF)
        sim_says(st, "position_valid", "True", 90)          # the FC fuses the VIO's odometry
        est = g.recv("ESTIMATOR_STATUS", lambda m: m.flags & REL, timeout_s=15)
        assert not est.flags & ABS and not est.flags & M.ESTIMATOR_PRED_POS_HORIZ_ABS
        assert est.pos_horiz_accuracy > 0
        raw = g.recv("GPS_RAW_INT", timeout_s=5)             # still no fix while flying on vision
        assert raw.fix_type == M.GPS_FIX_TYPE_NO_FIX and raw.satellites_visible == 0
    finally:
        g.close()
