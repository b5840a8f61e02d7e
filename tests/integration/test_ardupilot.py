"""The stack flying real ArduPilot: `aero up --profile ardupilot` runs ArduCopter SITL (physics inside
the binary) from the `ardupilot_dir` fixture (../shared/ardupilot's tarball, unpacked once per
session) as a supervised process beside fmu, planner, mission and diagnostics.

A hop through the stack (`aero mission fly`: arm, GUIDED, take-off 5 m, one waypoint 5 m east, LAND),
judged by ArduPilot's own truth, never by the stack's account: SIM_STATE (common message 108, which
ArduPilot SITL fills from its physics: lat_int/lon_int/alt; SIMSTATE of the ardupilotmega dialect has no
altitude) on ArduPilot's SERIAL1 (TCP 5762+10N, connected over 127.0.0.1 only), and its heartbeat for
armed. ArduPilot refuses arming until EKF3 uses GPS (~40 s after it starts): the test waits for fmu's
`ready_to_arm` (services/fmu/ardupilot.py) and a connected state/vehicle, bounded.
"""
from __future__ import annotations

import json
import math
import subprocess
import threading
import time

import pytest
from pymavlink import mavutil

from aerotest import aero_argv, clean_env, wait_until
from aeroperception.schemas import VehicleState
from aeroperception.tools.cli import ardupilot_sitl

pytestmark = [pytest.mark.ardupilot, pytest.mark.slow]

SERVICES = ["ardupilot", "fmu", "planner", "mission", "diagnostics"]
TAKEOFF_M = 5.0
TARGET_EN_M = (5.0, 0.0)        # the waypoint: 5 m east of home, at TAKEOFF_M (ENU x east, y north)
TOLERANCE_M = 0.5
EARTH_R_M = 6378137.0


class SimTruth:
    """ArduPilot SITL's SIM_STATE (truth) as (t, east, north, up) metres about its first sample (the
    vehicle on its pad), and its heartbeat's armed flag, from a client link on SERIAL1."""

    def __init__(self, port: int):
        self.conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=254, source_component=190,
                                               retries=20)
        self.track: list[tuple[float, float, float, float]] = []
        self.armed: bool | None = None
        self.home: tuple[float, float, float] | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        asked = 0.0
        while not self.stop.is_set():
            if time.monotonic() - asked > 2.0:   # SIM_STATE at 20 Hz on this link (asked until it comes)
                asked = time.monotonic()
                if not self.track:
                    self.conn.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                    mavutil.mavlink.MAVLINK_MSG_ID_SIM_STATE, 50000, 0, 0, 0, 0, 0)
            m = self.conn.recv_match(type=["SIM_STATE", "HEARTBEAT"], blocking=True, timeout=0.2)
            if m is None or m.get_srcSystem() != 1:
                continue
            if m.get_type() == "HEARTBEAT":
                if m.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
                    self.armed = bool(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                continue
            lat, lon = m.lat_int / 1e7, m.lon_int / 1e7
            if self.home is None:
                self.home = (lat, lon, m.alt)
            h_lat, h_lon, h_alt = self.home
            north = math.radians(lat - h_lat) * EARTH_R_M
            east = math.radians(lon - h_lon) * EARTH_R_M * math.cos(math.radians(h_lat))
            self.track.append((time.monotonic(), east, north, m.alt - h_alt))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.conn.close()


@pytest.fixture(scope="module")
def ardupilot(stack_module, ardupilot_dir, tmp_path_factory):
    instance = ardupilot_sitl.free_instance(1)
    assert instance is not None, "no free ArduPilot instance in 1..9"
    state_dir = tmp_path_factory.mktemp("mission-state")
    t0 = time.monotonic()
    st = stack_module(SERVICES, profile="ardupilot", timeout_s=60, extra_args=[
        "--ardupilot", str(ardupilot_dir), "--ardupilot-instance", str(instance),
        "--arg", f"mission:--param=state_dir={state_dir}"])
    truth = SimTruth(ardupilot_sitl.tcp_ports(instance)[1])
    try:
        try:
            wait_until(lambda: str(_diag_value(st, "ready_to_arm")) == "True", 90,
                       "fmu: ArduPilot ready to arm (pre-arm checks pass, EKF3 using GPS)")
            wait_until(lambda: st.latest("state/vehicle", VehicleState, 2.0, lambda m: m.connected), 20,
                       "state/vehicle connected (fmu <-> ArduPilot)")
        except BaseException:
            print(st.describe())
            raise
        st.ready_after_s = time.monotonic() - t0
        st.sim_truth = truth
        yield st
    finally:
        truth.close()


def _diag_value(st, key: str):
    return st.latest_diag("fmu", 2.0).values.get(key)


def test_takeoff_goto_land_on_arducopter_by_its_own_truth(ardupilot, tmp_path):
    st, truth = ardupilot, ardupilot.sim_truth
    mission = tmp_path / "hop.json"
    mission.write_text(json.dumps({
        "mission_id": "ardupilot_hop", "takeoff_altitude_m": TAKEOFF_M, "waypoint_acceptance_radius_m": 0.3,
        "waypoints": [{"x": TARGET_EN_M[0], "y": TARGET_EN_M[1], "z": TAKEOFF_M, "yaw_deg": 0.0}]}))
    t0 = time.monotonic()
    r = subprocess.run(aero_argv() + ["mission", "fly", str(mission), "--quiet", "--timeout", "70"],
                       env=clean_env(st.endpoint), capture_output=True, text=True, timeout=90,
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 0, f"aero mission fly: exit {r.returncode}\n{r.stdout}{r.stderr}\n{st.describe()}"
    wait_until(lambda: truth.armed is False, 15, "ArduPilot disarmed (its heartbeat)")
    flight_s = time.monotonic() - t0
    track = [p for p in truth.track if p[0] >= t0]
    assert track, "no SIM_STATE during the flight"
    # at the waypoint: the closest the truth came to it, at altitude
    err = min(math.dist((e, n, u), (*TARGET_EN_M, TAKEOFF_M)) for _t, e, n, u in track)
    top = max(u for *_x, u in track)
    _t, e_end, n_end, u_end = truth.track[-1]
    print(f"ArduPilot: ready to arm after {st.ready_after_s:.1f} s; flight {flight_s:.1f} s; "
          f"closest to the waypoint {err:.2f} m (truth); highest {top:.2f} m; landed at "
          f"({e_end:.2f}, {n_end:.2f}, {u_end:.2f}) m ENU from the pad")
    assert err < TOLERANCE_M, f"never within {TOLERANCE_M} m of the waypoint by SIM_STATE: closest {err:.2f} m"
    assert abs(top - TAKEOFF_M) < 1.0, f"climbed to {top:.2f} m, asked {TAKEOFF_M} m"
    assert abs(u_end) < 0.3, f"not on the ground by truth: {u_end:.2f} m"
    assert math.dist((e_end, n_end), TARGET_EN_M) < 1.0, "landed away from the waypoint"
    fmu = st.latest_diag("fmu", 3.0)     # ArduPilot's boot console text on SERIAL0 is not bad input
    assert "dropped invalid input" not in fmu.message and int(fmu.values.get("fc_console_bytes", 0)) > 0, fmu
