"""Trajectories flown on the built-in sim, judged by its truth: survey_01 with the smooth generator
faster than goal by goal at the same 2 m/s cap and on its legs; figure8 at 3 m/s; limits kept;
every waypoint passed and landed; a POLYNOMIAL trajectory through the SetTrajectory action, and
the goals it refuses; the planner's swappable parts switched over planner/srv/select_plugin on
the ground and hovering, refused moving; mission/uav_status along the way."""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from aeroperception.schemas import (
    GoalStatus, Header, ParamSet, ParamSetReply, PoseStamped, SelectPluginReply, SelectPluginRequest, SetTrajectoryFeedback, SetTrajectoryGoal,
    TakeoffGoal, Trajectory, TrajectorySetpoint, TrajectoryStatus, UAVMode, UAVStatus, VehicleState, WaypointReached,
    load_mission_file,
)
from aeroperception.services.runtime import ActionClient, call
from aeroperception.tools.eval.trajectory import TrajectoryEval
from aerotest import is_service_process, wait_until
from test_flight import REPO, SURVEY, flight_stack, fly_in_background, wait_at_rest

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
    stops = reference_stops(setpoints)
    print(f"{mission.mission_id} smooth: {res}; reference stopped mid-path {len(stops)} time(s) from {stops} m/s")
    assert [w.index for _, w in reached] == list(range(len(mission.waypoints)))
    assert truth[-1][1].position_m.z < 0.2 and not truth[-1][1].armed
    assert flown, "never flown as a trajectory"
    assert any(sp.acceleration_valid and sp.position_valid for sp in setpoints), "no feed-forward sent"
    return res, setpoints


def reference_stops(setpoints: list) -> list[float]:
    """The speeds (m/s) from which the streamed reference stopped dead mid-flight (a full-state
    setpoint with zero velocity right after a moving one)."""
    speeds = [float(np.hypot(sp.velocity_mps.x, sp.velocity_mps.y)) for sp in setpoints if sp.velocity_valid]
    return [round(a, 2) for a, b in zip(speeds, speeds[1:]) if a > 0.5 and b < 1e-6]


def test_survey_01_smooth_is_faster_and_on_its_legs(tstack):
    res, _ = fly_and_score(tstack, SURVEY, "--trajectory", "smooth")
    # goal by goal takes ~36 s for these legs at the 2 m/s cap: 30 % faster is < 25 s
    assert res["time_s"] < 25.0, res
    assert res["cross_track_rms_m"] < 0.25 and res["cross_track_max_m"] < 0.6, res
    assert res["peak_xy_speed_mps"] < 2.0 * 1.1 and res["peak_xy_acc_mps2"] < 3.0 * 1.1, res
    # 3-D, by truth: the take-off hands over climbing, and the path goes on at that velocity (from
    # rest the setpoint stepped 0.27 -> 0 m/s: 3.9-4.9 m/s³ vertical); 3.46 measured, all of it horizontal
    assert res["peak_jerk_mps3"] < 4.0 * 1.1, res


def stall_mission_once(st, after_reached: int, stall_s: float) -> tuple[threading.Thread, list]:
    """The mission process stopped for `stall_s` once `after_reached` waypoints are counted: what a
    loaded host does to it (state/vehicle reaches it late, not missing). Returns the thread and
    what it saw (errors, or the pid stalled)."""
    seen: list = []

    def run() -> None:
        try:
            with st.capture(reached=("mission/waypoint_reached", WaypointReached)) as rec:
                wait_until(lambda: len(rec.get("reached")) >= after_reached, 90, f"{after_reached} waypoints counted")
            pid = st.pids()["mission"]
            assert is_service_process(pid, "mission")
            os.kill(pid, signal.SIGSTOP)
            try:
                time.sleep(stall_s)
            finally:
                os.kill(pid, signal.SIGCONT)
            seen.append(pid)
        except Exception as e:  # noqa: BLE001 - reported by the test
            seen.append(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, seen


@pytest.mark.known_flaky   # under CPU load the reference stops dead from 2.7-3.0 m/s mid-figure. One cause fixed
#                            (the mission's own stall whose backlog came a tick late held it: OutageWatch); with three
#                            other stacks beside it (load 6-13) state/vehicle still arrives >0.5 s late or the FC link
#                            blips 0.4 s: the mission holds as designed and the planner brakes. Open in the issue notes.
def test_figure8_at_3_mps_tracks_its_reference(tstack):
    """Also through a late vehicle state mid-figure (the mission stalled 0.7 s, as under load:
    it holds, then resumes, handing the same waypoints over again): the planner resumes the path
    it was flying instead of one anew from rest, which braked the vehicle from 2.5 m/s (3.4-3.6
    m/s², 14.5 m/s³, 42.7-43.5 s; 1.98 m/s², 3.4 m/s³, 39.2 s resumed)."""
    r = tstack.aero("param", "set", "planner", "max_velocity_mps", "3.0", timeout_s=20)
    assert r.returncode == 0, r.stdout + r.stderr
    stall, seen = stall_mission_once(tstack, 8, 0.7)
    try:
        res, setpoints = fly_and_score(tstack, FIGURE8)           # the file asks for the smooth generator itself
    finally:
        tstack.aero("param", "set", "planner", "max_velocity_mps", "2.0", timeout_s=20)
        stall.join(5)
    assert seen and isinstance(seen[0], int), seen
    assert not reference_stops(setpoints), reference_stops(setpoints)
    # tracking by truth: off the legs (cross-track, the eval's figure) within 0.3 m RMS; against the
    # reference in time (along-track lag included) 0.29 m RMS measured: bounded at 0.45 m
    assert res["cross_track_rms_m"] < 0.3 and res["reference_error_rms_m"] < 0.45, res
    assert res["peak_xy_speed_mps"] < 3.0 * 1.1 and res["peak_xy_acc_mps2"] < 3.0 * 1.1, res
    assert res["peak_jerk_mps3"] < 4.0 * 1.1, res        # 3.56 measured (3-D = horizontal: no hand-over step)


def cubic_x(x0: float, y0: float, z0: float, distance_m: float, duration_s: float, **kw) -> Trajectory:
    """x from x0 to x0 + distance, at rest at both ends (3u^2 - 2u^3), as one POLYNOMIAL segment."""
    d, t = distance_m, duration_s
    return Trajectory(trajectory_id="cubic", trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=t,
                      poly_order=3, poly_coeffs_x=[x0, 0.0, 3 * d / t ** 2, -2 * d / t ** 3],
                      poly_coeffs_y=[y0, 0, 0, 0], poly_coeffs_z=[z0, 0, 0, 0],
                      setpoint_type=Trajectory.SETPOINT_FULL_STATE, **kw)


def set_planner(st, name: str, value) -> None:
    r = call(st.session, "config/planner/@set", ParamSet(name=name, value=value), ParamSetReply, 10)
    assert r.success, r.message


def select(st, role: str, name: str) -> SelectPluginReply:
    """SetController / SetEstimator / SetTrajectoryGenerator over Zenoh."""
    return call(st.session, "planner/srv/select_plugin", SelectPluginRequest(role=role, name=name), SelectPluginReply, 10)


def test_set_trajectory_action_flies_a_polynomial_and_refuses_what_it_cannot(tstack):
    st = tstack
    st.ensure_landed()
    takeoff = ActionClient(st.session, "mission/action/takeoff")
    fly = ActionClient(st.session, "mission/action/set_trajectory")
    try:
        with st.capture(setpoints=("fmu/in/trajectory_setpoint", TrajectorySetpoint)) as rec:
            r = select(st, "estimator", "gps")
            assert not r.success and "'gps' is not one of ['fc', 'vio']" in r.message and r.active == "fc", r
            r = select(st, "estimator", "vio")      # no VIO in this stack
            assert not r.success and "visual_odometry" in r.message and r.active == "fc", r
            r = select(st, "controller", "velocity")                     # on the ground: allowed
            assert r.success and r.active == "velocity", r
            t = time.monotonic()
            wait_until(lambda: len(rec.get("setpoints", since=t)) > 5, 5, "setpoints after the switch")
            assert not any(sp.position_valid for sp in rec.get("setpoints", since=t)[2:])   # velocity only now
            assert select(st, "controller", "feedforward").success
        g = takeoff.send_goal(TakeoffGoal(target_altitude_m=3.0))
        assert g.success, g.message
        assert takeoff.result(g.goal_id, 40).status == GoalStatus.SUCCEEDED
        here = wait_at_rest(st).position_m
        x0, y0, z0 = here.x, here.y, here.z
        r = select(st, "trajectory_generator", "smooth")                 # hovering: allowed
        assert r.success and r.active == "smooth", r
        assert select(st, "trajectory_generator", "waypoint").success
        uav = st.capture(uav=("mission/uav_status", UAVStatus))
        with uav:
            wait_until(lambda: uav.last("uav") is not None, 5, "mission/uav_status")
        hovering = uav.last("uav")
        assert hovering.current_mode.state == UAVMode.STATE_HOVERING and hovering.current_mode.can_land, hovering
        assert hovering.active_controller == "feedforward" and hovering.active_trajectory_generator == "waypoint"
        odom_wp = Trajectory(generator_name="smooth", waypoints=[PoseStamped(header=Header(frame_id="odom"))])
        for goal, why in [
            (SetTrajectoryGoal(trajectory=cubic_x(x0, y0, z0, 6.0, 8.0), replace_current=False), "replace_current"),
            (SetTrajectoryGoal(trajectory=cubic_x(x0, y0, z0, 6.0, 8.0, start_time_ns=5)), "start_time_ns"),
            (SetTrajectoryGoal(trajectory=cubic_x(x0 + 20, y0, z0, 6.0, 8.0)), "starts 20"),
            (SetTrajectoryGoal(trajectory=cubic_x(x0, y0, z0, 60.0, 2.0)), "MPC_XY_VEL_MAX"),
            (SetTrajectoryGoal(trajectory=odom_wp), "`waypoints[0].header.frame_id` 'odom'"),
        ]:
            r = fly.send_goal(goal)
            assert not r.success and why in r.message, (why, r.message)
        # The planner's live limit below the trajectory's speed (1.1 m/s peak): accepted by the mission
        # (default limits), refused by the planner, which holds: the action fails, never flown goal by goal.
        set_planner(st, "max_velocity_mps", 0.5)
        try:
            with st.capture(truth=("sim/truth/state", VehicleState)) as rec:
                r = fly.send_goal(SetTrajectoryGoal(trajectory=cubic_x(x0, y0, z0, 6.0, 8.0)))
                assert r.success, r.message
                res = fly.result(r.goal_id, 20)
                assert res.status == GoalStatus.ABORTED and "MPC_XY_VEL_MAX" in res.message, res.message
                moved = max(abs(m.position_m.x - x0) for m in rec.get("truth"))
            assert moved < 0.3, f"flew {moved:.2f} m towards a refused trajectory's end"
        finally:
            set_planner(st, "max_velocity_mps", 2.0)
        feedback: list = []
        with st.capture(truth=("sim/truth/state", VehicleState), uav=("mission/uav_status", UAVStatus)) as rec:
            r = fly.send_goal(SetTrajectoryGoal(trajectory=cubic_x(x0, y0, z0, 6.0, 8.0)), feedback_cb=feedback.append)
            assert r.success, r.message
            wait_until(lambda: (rec.last("truth") is not None and rec.last("truth").velocity_mps.x > 0.6), 10,
                       f"moving along the trajectory (mission {st.mission_state()})")
            moving = select(st, "controller", "velocity")                # moving: refused
            assert not moving.success and "moving at" in moving.message and moving.active == "feedforward", moving
            res = fly.result(r.goal_id, 40)
            assert res.status == GoalStatus.SUCCEEDED, f"{GoalStatus.name(res.status)}: {res.message}"
            track = np.array([m.position_m.to_array() for m in rec.get("truth")])
            modes = [(m.current_mode.state, m.current_mode.control_mode) for m in rec.get("uav")]
        end = np.array([x0 + 6.0, y0, z0])
        assert np.linalg.norm(track - end, axis=1).min() < 0.35        # done within 0.3 m of its end (estimate)
        assert np.abs(track[:, 1] - y0).max() < 0.3 and np.abs(track[:, 2] - z0).max() < 0.4   # along its line
        statuses = [f.unwrap(SetTrajectoryFeedback).status for f in feedback]
        assert any(s.trajectory_id == "cubic" and s.progress_percent > 50 for s in statuses), statuses[-3:]
        assert (UAVMode.STATE_FLYING, UAVMode.MODE_TRAJECTORY) in modes, modes
        assert st.mission_state() == "HOLDING"
    finally:
        takeoff.close()
        fly.close()
        st.ensure_landed()


@pytest.mark.extended
def test_a_planner_killed_mid_trajectory_holds_and_the_restarted_one_flies_the_rest(tstack):
    """SIGKILL the planner while survey_01 is flown smooth at speed: the mission holds (planner
    outage), `aero up` restarts the planner, START resumes at the waypoint then current and the
    new planner makes a new trajectory from where the vehicle is: every waypoint reached, landed.
    A part switched live before the flight (generator smooth over the default waypoint) is what the
    restarted planner runs: restored from the state directory, not its start-up value."""
    st = tstack
    st.ensure_landed()
    assert select(st, "trajectory_generator", "smooth").success
    with st.capture(truth=("sim/truth/state", VehicleState), reached=("mission/waypoint_reached", WaypointReached)) as rec, \
            fly_in_background(st, SURVEY, "--trajectory", "smooth", "--timeout", "150") as (proc, out):
        wait_until(lambda: len(rec.get("reached")) >= 2 and rec.last("truth") is not None
                   and np.linalg.norm(rec.last("truth").velocity_mps.to_array()) > 1.0, 60, "flying the second leg fast")
        pid = st.pids()["planner"]
        assert is_service_process(pid, "planner")
        os.kill(pid, signal.SIGKILL)
        wait_until(lambda: st.pids().get("planner") not in (None, pid), 20, "aero up restarted the planner")
        restarted = st.latest("planner/status", TrajectoryStatus, 10.0)
        assert restarted is not None and restarted.active_trajectory_generator == "smooth", restarted
        wait_until(lambda: st.mission_state() == "HOLDING", 10, "the mission holding through the planner outage")
        wait_at_rest(st)
        assert st.command("START").success
        assert proc.wait(120) == 0, "".join(out[-20:])
        reached = sorted({w.index for _, w in rec.since("reached")})
        truth = rec.last("truth")
    assert select(st, "trajectory_generator", "waypoint").success    # landed: back to the default
    assert reached == [0, 1, 2, 3], (reached, "".join(out[-20:]))
    assert truth.position_m.z < 0.2 and not truth.armed
