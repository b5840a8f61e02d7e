"""Missions flown with the smooth trajectory generator on the built-in sim, judged by its truth:
survey_01 faster than goal by goal at the same 2 m/s cap and on its legs; figure8 at 3 m/s
tracking its reference; limits kept; every waypoint passed and landed."""
from __future__ import annotations

import time

import numpy as np
import pytest

from aeroperception.schemas import (
    TrajectorySetpoint, TrajectoryStatus, VehicleState, WaypointReached, load_mission_file,
)
from aeroperception.tools.eval_trajectory import TrajectoryEval
from aerotest import wait_until
from test_flight import REPO, SURVEY, flight_stack

pytestmark = pytest.mark.slow

FIGURE8 = REPO / "examples" / "missions" / "figure8.json"


@pytest.fixture(scope="module")
def tstack(stack_module):
    return flight_stack(stack_module)


def fly_and_score(st, path, *fly_args: str) -> tuple[dict, list]:
    """Fly the mission file, then its figures (eval_trajectory on arrival times: one clock for
    truth and the mission's events) and the setpoints sent."""
    mission = load_mission_file(path)
    with st.capture(truth=("sim/truth/state", VehicleState), reached=("mission/waypoint_reached", WaypointReached),
                    status=("planner/status", TrajectoryStatus),
                    setpoints=("fmu/in/trajectory_setpoint", TrajectorySetpoint)) as rec:
        r = st.aero("mission", "fly", str(path), *fly_args, "--quiet", "--timeout", "150", timeout_s=180)
        assert r.returncode == 0, f"fly exit {r.returncode}\n{r.stdout}\n{r.stderr}\n{st.describe()}"
        wait_until(lambda: rec.last("truth") is not None and not rec.last("truth").armed, 10, "disarmed")
        time.sleep(0.3)
        truth, reached = rec.since("truth"), rec.since("reached")
        statuses, setpoints = rec.get("status"), rec.get("setpoints")
    ev = TrajectoryEval(np.array([[w.x, w.y, w.z] for w in mission.waypoints], float))
    for t, m in truth:
        ev.add_truth(t, m.position_m.to_array(), m.velocity_mps.to_array(), m.header.stamp_ns * 1e-9)
    for t, w in reached:
        ev.add_reached(w.index, t)
    flown = [s for s in statuses if s.trajectory_id.startswith(f"{mission.mission_id}@")]
    for s in flown:
        if s.status == TrajectoryStatus.STATUS_EXECUTING:
            ev.add_reference_error(s.position_error_m)
    res = ev.summary()
    print(f"{mission.mission_id} smooth: {res}")
    assert [w.index for _, w in reached] == list(range(len(mission.waypoints)))
    assert truth[-1][1].position_m.z < 0.2 and not truth[-1][1].armed
    assert flown, "never flown as a trajectory"
    assert any(sp.acceleration_valid and sp.position_valid for sp in setpoints), "no feed-forward sent"
    return res, setpoints


def test_survey_01_smooth_is_faster_and_on_its_legs(tstack):
    res, _ = fly_and_score(tstack, SURVEY, "--trajectory", "smooth")
    # goal by goal takes ~36 s for these legs at the 2 m/s cap: 30 % faster is < 25 s
    assert res["time_s"] < 25.0, res
    assert res["cross_track_rms_m"] < 0.25 and res["cross_track_max_m"] < 0.6, res
    assert res["peak_xy_speed_mps"] < 2.0 * 1.1 and res["peak_xy_acc_mps2"] < 3.0 * 1.1, res


def test_figure8_at_3_mps_tracks_its_reference(tstack):
    r = tstack.aero("param", "set", "planner", "max_velocity_mps", "3.0", timeout_s=20)
    assert r.returncode == 0, r.stdout + r.stderr
    try:
        res, _ = fly_and_score(tstack, FIGURE8)           # the file asks for the smooth generator itself
    finally:
        tstack.aero("param", "set", "planner", "max_velocity_mps", "2.0", timeout_s=20)
    # tracking by truth: off the legs (cross-track, the eval's figure) within 0.3 m RMS; against the
    # reference in time (along-track lag included) 0.29 m RMS measured: bounded at 0.45 m
    assert res["cross_track_rms_m"] < 0.3 and res["reference_error_rms_m"] < 0.45, res
    assert res["peak_xy_speed_mps"] < 3.0 * 1.1 and res["peak_xy_acc_mps2"] < 3.0 * 1.1, res
