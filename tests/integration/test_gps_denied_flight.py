"""GPS-denied flight on the real stack: `aero up --gps-denied --scenario village` (sim, fmu, planner,
mission, vio, perception as processes; LiDAR, gcs, safety left out to save CPU). The simulated
flight controller has no GPS-like position: it flies on the VIO that fmu injects as ODOMETRY,
fused with its IMU. Ground truth comes from sim/truth/state, never from the autonomy.

One module-scoped stack, flights in order (each lands before the next):
- camera blackout 3 s while EXECUTING: VIO LOST -> perception unhealthy -> mission HOLDING ->
  cameras back, VIO TRACKING -> EXECUTING again -> mission completes and lands.
- camera blackout 15 s with the FC on its GPS-like position (SIM_GPS_DENIED off for that test):
  HOLDING, no recovery within perception_recovery_s (10 s) -> RTL -> landed at home. GPS-denied,
  the FC itself gives up first: PX4's "No valid position estimate" failsafe LAND after
  EKF2_NOAID_TOUT (5 s) of dead-reckoning (unit tested in tests/unit/test_sim_gps_denied.py).
- the Done-when survey (opt-in marker vio_e2e, ~4 min; first: on a fresh VIO, as after `aero up`): examples/missions/village_survey_gps_denied.json (>= 150 m) flown
  to completion on VIO alone, every waypoint reached per truth, landed; `aero eval vio --live`
  over the flight: drift < 1 %, ATE RMSE < 0.5 m, position NEES between 1 and 9.
"""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from aerotest import Capture, aero_argv, clean_env, free_udp_port, wait_until
from aeroperception.schemas import (
    DiagnosticStatus, MissionStatus, PerceptionHealth, SelectPluginReply, SelectPluginRequest, TrajectoryStatus,
    VehicleState, VioHealth, load_mission_file,
)
from aeroperception.services.runtime import call

REPO = Path(__file__).resolve().parents[2]
SURVEY = REPO / "examples" / "missions" / "village_survey_gps_denied.json"
SERVICES = ["sim", "fmu", "planner", "mission", "vio", "perception"]
# Slower than real time (services follow sim/clock): the cameras render and the VIO runs at their
# rates on a loaded 2-core machine; below 1 every service also uses sim time, so the VIO's age at
# fmu is measured on the sim clock even when the physics had to re-anchor.
SPEED = 0.5


def sim_flag(st, name: str) -> bool:
    """A boolean of the sim's diagnostics (values travel as text)."""
    d = st.latest("diagnostics/sim", DiagnosticStatus, 3.0)
    assert d is not None, "no diagnostics/sim"
    return str(d.values.get(name)) == "True"


@pytest.fixture(scope="module")
def gstack(stack_module):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack_module(SERVICES, extra_args=[
        "--gps-denied", "--scenario", "village", "--sensors", "camera", "--speed", str(SPEED),
        "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
        "--arg", "sim:--param=RTL_RETURN_ALT=6"], timeout_s=60)
    try:
        wait_until(lambda: st.latest("state/vehicle", VehicleState, 1.0, lambda m: m.connected),
                   30, "state/vehicle connected (fmu <-> sim MAVLink)")
        wait_until(lambda: st.latest("perception/health", PerceptionHealth, 1.5, lambda m: m.overall_healthy),
                   60, "perception healthy (VIO TRACKING on the ground)")
        wait_until(lambda: sim_flag(st, "position_valid"), 15,
                   "the GPS-denied FC has a position from the VIO")
    except BaseException:
        print(st.describe())
        raise
    return st


def record(st) -> Capture:
    return st.capture(truth=("sim/truth/state", VehicleState), status=("mission/status", MissionStatus),
                      vio=("state/vio_health", VioHealth))


def fly(st, mission: Path, timeout_s: float = 200.0) -> subprocess.Popen:
    return subprocess.Popen(aero_argv() + ["mission", "fly", str(mission), "--quiet", "--timeout", str(int(timeout_s))],
                            env=clean_env(st.endpoint), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)


def finish(p: subprocess.Popen, timeout_s: float) -> tuple[int, str]:
    try:
        out, err = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
        return -1, (out or "") + (err or "")
    return p.returncode, (out or "") + (err or "")


def distinct(seq: list) -> list:
    return [s for k, s in enumerate(seq) if k == 0 or s != seq[k - 1]]


def line_mission(tmp_path: Path, length_m: float) -> Path:
    p = tmp_path / "line.json"
    p.write_text(json.dumps({"mission_id": "line", "takeoff_altitude_m": 4.0, "waypoint_acceptance_radius_m": 1.0,
                             "waypoints": [{"x": 2.0, "y": 0.0, "z": 4.0}, {"x": length_m, "y": 0.0, "z": 4.0},
                                           {"x": 2.0, "y": 0.0, "z": 4.0}]}))
    return p


def blackout_when_executing(st, rec: Capture, seconds: float, after_s: float = 3.0,
                            past_x_m: float | None = None) -> float:
    """SIM_CAM_BLACKOUT `seconds` once the mission is EXECUTING: `after_s` later, or (`past_x_m`) as
    soon as the true track is east of that x (under way on the line's outbound leg)."""
    wait_until(lambda: rec.last("status") is not None and rec.last("status").state == "EXECUTING", 60,
               "mission EXECUTING")
    if past_x_m is None:
        time.sleep(after_s)
    else:
        wait_until(lambda: rec.last("truth").position_m.x > past_x_m, 30, f"under way east of x = {past_x_m} m")
    r = st.aero("param", "set", "sim", "SIM_CAM_BLACKOUT", str(seconds))
    assert r.returncode == 0, r.stderr
    return time.monotonic()


@pytest.mark.slow
@pytest.mark.vio_e2e
@pytest.mark.timeout(600)
def test_village_survey_on_vio_alone(gstack, tmp_path):
    st = gstack
    wait_until(lambda: sim_flag(st, "position_valid") and sim_flag(st, "gps_denied"),
               15, "GPS-denied FC with a vision position")
    mission = load_mission_file(SURVEY)
    wps = np.array([[w.x, w.y, w.z] for w in mission.waypoints])
    path_m = float(np.sum(np.linalg.norm(np.diff(np.vstack([[0, 0, mission.takeoff_altitude_m], wps]), axis=0), axis=1)))
    assert path_m >= 150.0
    rec = record(st)
    out_dir = tmp_path / "eval"
    t0 = time.monotonic()
    try:
        ev = subprocess.Popen(aero_argv() + ["eval", "vio", "--live", "--until-landed", "--duration", "400",
                                             "--out", str(out_dir)],
                              env=clean_env(st.endpoint), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, stdin=subprocess.DEVNULL)
        time.sleep(1.0)
        p = fly(st, SURVEY, 400)
        code, out = finish(p, 420)
        flight_s = time.monotonic() - t0
        assert code == 0, f"fly exit {code}\n{out}\n{st.describe()}"
        wait_until(lambda: st.landed(0.1), 20, "landed and disarmed per truth")
        track = np.array([m.position_m.to_array() for m in rec.get("truth")])
        final = rec.last("truth")
        ev_code, ev_out = finish(ev, 30)
    finally:
        rec.close()
        if ev.poll() is None:
            ev.kill()
    closest = [float(np.linalg.norm(track - wp, axis=1).min()) for wp in wps]
    print(f"village survey {path_m:.0f} m GPS-denied: {flight_s:.0f} s wall; closest true approach (m): "
          f"{[round(c, 2) for c in closest]}\n{ev_out}")
    # Reached per truth: within the acceptance radius (judged by the FC's estimate) plus the drift
    # budget of the Done-when (1 % of the path flown to that waypoint): VIO error is flight error.
    legs = np.linalg.norm(np.diff(np.vstack([[0, 0, mission.takeoff_altitude_m], wps]), axis=0), axis=1)
    budget = mission.waypoint_acceptance_radius_m + 0.01 * np.cumsum(legs)
    assert np.all(np.array(closest) < budget), (closest, budget.round(2).tolist())
    assert final.position_m.z < 0.1 and not final.armed
    assert ev_code == 0, ev_out
    m = json.loads((out_dir / "vio_eval.json").read_text())
    assert m["distance_m"] > 150.0, m["distance_m"]
    assert m["drift_pct"] < 1.0, m["drift_pct"]
    assert m["ate_rmse_m"] < 0.5, m["ate_rmse_m"]
    assert 1.0 <= m["nees_position_mean"] <= 9.0, m["nees_position_mean"]


@pytest.mark.slow
def test_blackout_3s_holds_then_resumes(gstack, tmp_path):
    st = gstack
    assert sim_flag(st, "gps_denied")
    rec = record(st)
    try:
        # 2 -> 10 -> 2 m, the blackout just past x = 2.5 m on the way out: it holds well short of the far
        # end (x = 4-5 m), so reaching it proves the resumed leg was flown, and the leg back after it
        p = fly(st, line_mission(tmp_path, 10.0), 150)
        t_black = blackout_when_executing(st, rec, 3.0, past_x_m=2.5)
        code, out = finish(p, 180)
        assert code == 0, f"fly exit {code}\n{out}\n{st.describe()}"
        wait_until(lambda: st.landed(0.1), 20, "landed and disarmed per truth")
        wait_until(lambda: rec.last("status").state == "IDLE", 10, "mission IDLE after the landing")
        vio = distinct([m.state_name for m in rec.get("vio", t_black)])
        states = distinct([m.state for m in rec.get("status", t_black - 1.0)])   # EXECUTING before it
        track = np.array([m.position_m.to_array() for m in rec.get("truth")])
        t_hold = next((t for t, m in rec.since("status", t_black) if m.state == "HOLDING"), None)
        x_hold = rec.get("truth", t_hold)[0].position_m.x if t_hold is not None else None
    finally:
        rec.close()
    print(f"VIO after the blackout: {vio}; mission: {states}; HOLDING at true x = {x_hold} m")
    assert "LOST" in vio and vio[-1] == "TRACKING", vio
    k = states.index("HOLDING")
    assert k > 0 and states[k - 1] == "EXECUTING" and states[k + 1] == "EXECUTING", states
    assert states[-1] == "IDLE" and "LAND" in states
    # the far end was still flown after the hold (within the VIO drift the module's flights have accumulated)
    assert x_hold is not None and x_hold < 7.0, x_hold
    assert np.linalg.norm(track[:, :2] - [10.0, 0.0], axis=1).min() < 3.0


@pytest.mark.slow
@pytest.mark.extended   # 63 s; the 3 s blackout (LOST -> HOLDING -> resume) runs by default, the RTL rule is unit-tested
def test_blackout_15s_returns_home_and_lands(gstack, tmp_path):
    """The mission's policy, with the FC on its GPS-like position so RTL can fly (GPS-denied, the
    FC's own no-position failsafe lands it first: see the module docstring)."""
    st = gstack
    assert st.aero("param", "set", "sim", "SIM_GPS_DENIED", "false").returncode == 0
    rec = record(st)
    try:
        p = fly(st, line_mission(tmp_path, 30.0), 150)
        t_black = blackout_when_executing(st, rec, 15.0, after_s=4.0)
        x_black = rec.last("truth").position_m.x
        code, out = finish(p, 180)
        assert code == 0, f"fly exit {code}\n{out}\n{st.describe()}"
        wait_until(lambda: st.landed(0.1), 30, "landed and disarmed per truth")
        states = distinct([m.state for m in rec.get("status", t_black - 1.0)])
        msgs = [m.message for m in rec.get("status", t_black)]
        final = rec.last("truth")
        hold_s = [t for t, m in rec.since("status", t_black) if m.state == "LAND"]
    finally:
        rec.close()
        st.aero("param", "set", "sim", "SIM_GPS_DENIED", "true")
    print(f"mission after a 15 s blackout: {states}")
    assert states[:3] == ["EXECUTING", "HOLDING", "LAND"], states
    assert any("RTL" in m for m in msgs), msgs
    assert hold_s and hold_s[0] - t_black > 9.0, "RTL before perception_recovery_s"
    assert x_black > 3.0 and abs(final.position_m.x) < 1.5 and abs(final.position_m.y) < 1.5, \
        "RTL lands at home"
    assert final.position_m.z < 0.1 and not final.armed


@pytest.mark.slow
@pytest.mark.extended   # a 12 m line and back on the planner's `vio` estimator; the switch and its refusals run by default (test_trajectory_flight)
def test_the_planners_vio_estimator_flies_a_line_and_lands(gstack, tmp_path):
    """SetEstimator `vio`: the planner measures progress and error on VIO's odometry directly
    (aligned to the map with the FC's estimate when taken up); flown here, judged by truth."""
    st = gstack
    wait_until(lambda: st.latest("perception/health", PerceptionHealth, 1.5, lambda m: m.overall_healthy),
               60, "perception healthy (VIO TRACKING on the ground)")
    st.ensure_landed()
    r = call(st.session, "planner/srv/select_plugin", SelectPluginRequest(role="estimator", name="vio"),
             SelectPluginReply, 10)
    assert r.success and r.active == "vio", r.message
    rec = st.capture(truth=("sim/truth/state", VehicleState), planner=("planner/status", TrajectoryStatus))
    try:
        code, out = finish(fly(st, line_mission(tmp_path, 12.0)), 220)
        assert code == 0, f"fly exit {code}\n{out}\n{st.describe()}"
        wait_until(lambda: st.landed(0.1), 20, "landed and disarmed per truth")
        track = np.array([m.position_m.to_array() for m in rec.get("truth")])
        estimators = {s.active_estimator for s in rec.get("planner")}
        final = rec.last("truth")
    finally:
        rec.close()
        st.ensure_landed()
        back = call(st.session, "planner/srv/select_plugin", SelectPluginRequest(role="estimator", name="fc"),
                    SelectPluginReply, 10)
        assert back.success, back.message
    closest = [float(np.linalg.norm(track - wp, axis=1).min()) for wp in ([2.0, 0, 4.0], [12.0, 0, 4.0])]
    print(f"line on the planner's vio estimator: closest true approach {[round(c, 2) for c in closest]} m")
    assert estimators == {"vio"}, estimators
    assert max(closest) < 1.0 + 0.2, closest         # acceptance radius + VIO drift over ~25 m (1 %)
    assert final.position_m.z < 0.1 and not final.armed
