"""The planner's trajectory tracker against a mission that counts waypoints by distance."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import Header, Pose, PoseStamped, Quaternion, Trajectory, Vector3
from aeroperception.services.planner import contract
from aeroperception.services.planner.tracking import TrackerConfig, TrajectoryTracker, start_velocity_mps
from aeroperception.services.runtime.config import build
from aeroperception.services.lib.trajectory import KinematicLimits
from aeroperception.services.lib.trajectory.core import PlanningMargin, peaks

SURVEY = [(10, 0, 5), (10, 10, 5), (0, 0, 5)]
DT = 0.02


def wp(x, y, z, yaw=0.0) -> PoseStamped:
    return PoseStamped(header=Header(frame_id="map"),
                       pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion.from_yaw(yaw)))


def smooth_msg(points=SURVEY, tid="survey_01@0") -> Trajectory:
    return Trajectory(trajectory_id=tid, generator_name="smooth", setpoint_type=Trajectory.SETPOINT_FULL_STATE,
                      waypoints=[wp(*p) for p in points])


def tracker(radius=0.5) -> TrajectoryTracker:
    return TrajectoryTracker(build(TrackerConfig, contract.PARAMS, max_velocity_mps=2.0, acceptance_radius_m=radius,
                                   generator="smooth"))


def fly(tr: TrajectoryTracker, start, goals, radius=0.5, lag_s=0.0, max_s=120.0, blocked=None):
    """A vehicle that is where the reference was `lag_s` ago, a mission that advances its goal
    when the vehicle is within `radius`. Returns (time when the last goal was reached, reached times)."""
    pos, k, t, reached, history = np.array(start, float), 0, 0.0, [], []
    while t < max_s and k < len(goals):
        goal = np.array(goals[k], float)
        fs = tr.step(pos, 0.0, t, goal, blocked)
        if fs is None:       # goal by goal: a straight move at 1 m/s (the P-controller's part)
            d = goal - pos
            n = float(np.linalg.norm(d))
            target = pos + d / n * min(n, 1.0 * DT) if n > 1e-9 else pos
        else:
            target = fs.setpoint.position_m.to_array()
        history.append(target)
        lag = int(lag_s / DT)
        pos = history[-1 - lag] if len(history) > lag else np.array(start, float)
        if np.linalg.norm(pos - goal) < radius:
            reached.append(t)
            k += 1
        t += DT
    return t, reached


def test_a_smooth_trajectory_flies_every_waypoint_in_about_its_own_time():
    tr = tracker()
    tr.offer(smooth_msg())
    t, reached = fly(tr, (0, 0, 5), SURVEY)
    assert len(reached) == 3 and tr.built == 1
    assert t < tr.follower.path.duration_s + 0.5 < 24.0


def test_a_mission_that_ends_where_it_began_flies_its_last_leg():
    tr = tracker()
    loop = [(0, 0, 5), (10, 0, 5), (10, 10, 5), (0, 0, 5)]    # survey_01: waypoint 3 is waypoint 0
    tr.offer(smooth_msg(loop))
    t, reached = fly(tr, (0, 0.1, 5), loop)
    assert len(reached) == 4 and tr.built == 1 and t < tr.follower.path.duration_s + 0.5


def test_a_lagging_vehicle_still_reaches_every_waypoint_the_reference_waits_for_the_mission():
    tr = tracker()
    tr.offer(smooth_msg())
    _, reached = fly(tr, (0, 0, 5), SURVEY, radius=0.1, lag_s=0.6)     # a tight radius: corners are cut 0.25 m
    assert len(reached) == 3 and tr.built == 1


def test_a_goal_off_the_trajectory_takes_over_and_the_trajectory_resumes_from_the_vehicle():
    tr = tracker()
    tr.offer(smooth_msg())
    pos = np.array([0.0, 0, 5])
    assert tr.step(pos, 0.0, 0.0, np.array([10.0, 0, 5])) is not None
    assert tr.step(pos, 0.0, 0.1, np.array([3.0, 3.0, 5])) is None and tr.follower is None   # a goto
    fs = tr.step(np.array([3.0, 3.0, 5]), 0.0, 5.0, np.array([10.0, 10.0, 5]))   # back on: waypoint 1 on
    assert fs is not None and tr.built == 2 and tr.first_index == 1
    assert np.allclose(fs.reference.position_m, [3, 3, 5])                     # from where the vehicle is


def test_blocked_ahead_diverts_to_the_goal_then_a_new_path_from_the_next_goal():
    tr = tracker()
    tr.offer(smooth_msg())
    calls = {"n": 0}

    def blocked_once(ahead_xy):
        calls["n"] += 1
        return calls["n"] == 10            # an obstacle seen on the tenth check

    t, reached = fly(tr, (0, 0, 5), SURVEY, blocked=blocked_once)
    assert len(reached) == 3 and tr.built == 2      # diverted to waypoint 0 goal by goal, then a new path


def test_typed_trajectory_blocked_holds_saying_so_and_refusals_say_why():
    tr = tracker()
    typed = Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=10.0, poly_order=1,
                       poly_coeffs_x=[0, 1.0], poly_coeffs_y=[0, 0], poly_coeffs_z=[5, 0],
                       setpoint_type=Trajectory.SETPOINT_FULL_STATE)
    tr.offer(typed)
    end = np.array([10.0, 0, 5])
    assert tr.step(np.array([0.0, 0, 5]), 0.0, 0.0, end, lambda xy: False) is not None
    assert tr.step(np.array([0.0, 0, 5]), 0.0, 0.1, end, lambda xy: True) is None
    assert "blocked" in tr.blocked
    tr.offer(Trajectory(generator_name="min_snap", waypoints=[wp(5, 0, 5)]))
    assert tr.step(np.array([0.0, 0, 5]), 0.0, 0.0, np.array([5.0, 0, 5])) is None
    assert "generator_name" in tr.refused
    tr.offer(Trajectory())                          # the mission withdraws its trajectory
    assert tr.msg is None and tr.step(np.zeros(3), 0.0, 0.0, np.array([5.0, 0, 5])) is None


def test_heading_starts_at_the_vehicles_and_ends_at_the_last_waypoints_yaw():
    tr = tracker()
    tr.offer(smooth_msg([(5, 0, 5), (5, 5, 5, math.pi / 2)]))
    fs = tr.step(np.array([0.0, 0, 5]), 0.3, 0.0, np.array([5.0, 0, 5]))
    assert fs.setpoint.yaw_valid and fs.setpoint.yaw_rad == pytest.approx(0.3)
    path = tr.follower.path
    assert path.sample(path.duration_s).yaw_rad == pytest.approx(math.pi / 2)


def test_a_flight_controllers_velocity_error_is_planned_below_the_caps():
    """fc_velocity_error_mps: a generated path is timed that far below each speed cap (never below
    half of it) and the governor caps the FC's catch-up there too; a typed trajectory is checked
    against the limits themselves; 0 changes nothing."""
    limits = KinematicLimits(xy_vel_max_mps=2.0, z_vel_max_up_mps=3.0, z_vel_max_dn_mps=1.5)
    lowered = limits.inside(PlanningMargin(speed_mps=0.15))
    assert (lowered.xy_vel_max_mps, lowered.z_vel_max_up_mps, lowered.z_vel_max_dn_mps) == pytest.approx((1.85, 2.85, 1.35))
    assert (lowered.acc_hor_mps2, lowered.jerk_mps3) == (limits.acc_hor_mps2, limits.jerk_mps3)
    assert limits.inside(PlanningMargin()) is limits
    assert limits.inside(PlanningMargin(speed_mps=1.9)).xy_vel_max_mps == pytest.approx(1.0)   # half the cap at least
    peaks = {}
    for margin in (0.0, 0.15):
        tr = TrajectoryTracker(build(TrackerConfig, contract.PARAMS, max_velocity_mps=limits.xy_vel_max_mps, generator="smooth",
                                     fc_xy_gain_per_s=0.95, fc_velocity_error_mps=margin))
        tr.offer(smooth_msg())
        fly(tr, (0, 0, 5), SURVEY)
        path = tr.follower.path
        peaks[margin] = max(float(np.hypot(*path.sample(t).velocity_mps[:2])) for t in np.arange(0, path.duration_s, 0.02))
        assert tr.follower.governor.xy_speed_mps == pytest.approx(2.0 - margin)
    assert peaks[0.0] == pytest.approx(2.0, abs=1e-3) and peaks[0.15] == pytest.approx(1.85, abs=1e-3)


def test_a_flight_controllers_added_jerk_is_planned_below_the_jerk_limit():
    """fc_jerk_error_mps3: a generated path is planned that far below jerk_mps3 (never below half of
    it), so that the reference's jerk plus what the FC adds stays within the limit; speed and
    acceleration limits are untouched by it; 0 changes nothing."""
    limits = KinematicLimits(xy_vel_max_mps=3.0, acc_hor_mps2=3.0, jerk_mps3=4.0)
    lowered = limits.inside(PlanningMargin(jerk_mps3=1.0))
    assert lowered.jerk_mps3 == pytest.approx(3.0)
    assert (lowered.xy_vel_max_mps, lowered.acc_hor_mps2, lowered.z_vel_max_up_mps) == \
        (limits.xy_vel_max_mps, limits.acc_hor_mps2, limits.z_vel_max_up_mps)
    assert limits.inside(PlanningMargin(jerk_mps3=3.5)).jerk_mps3 == pytest.approx(2.0)   # half the limit at least
    both = limits.inside(PlanningMargin(0.2, 1.0))
    assert (both.xy_vel_max_mps, both.jerk_mps3) == pytest.approx((2.8, 3.0))
    jerks = {}
    for margin in (0.0, 1.0):
        tr = TrajectoryTracker(build(TrackerConfig, contract.PARAMS, max_velocity_mps=limits.xy_vel_max_mps, generator="smooth",
                                     fc_jerk_error_mps3=margin))
        tr.offer(smooth_msg())
        fly(tr, (0, 0, 5), SURVEY)
        jerks[margin] = peaks(tr.follower.path, 0.005).jerk_mps3
    # the blends are jerk-limited at the corners: the peak is the planning limit itself
    assert jerks[0.0] == pytest.approx(4.0, abs=0.02) and jerks[1.0] == pytest.approx(3.0, abs=0.02)



def test_a_path_made_while_the_vehicle_moves_starts_at_the_velocity_given():
    """The take-off hands over while the vehicle still climbs: the reference goes on at that
    velocity (no step), and the path still flies every waypoint."""
    tr = tracker()
    tr.offer(smooth_msg())
    fs = tr.step(np.array([0.0, 0, 4.7]), 0.0, 0.0, np.array([10.0, 0, 5]), velocity_mps=np.array([0, 0, 0.27]))
    assert np.allclose(fs.setpoint.velocity_mps.to_array(), [0, 0, 0.27]) and tr.built == 1
    _, reached = fly(tr, (0, 0, 4.7), SURVEY)
    assert len(reached) == 3 and tr.built == 1


def test_a_short_hold_resumes_the_path_a_long_one_starts_anew_from_rest():
    """A late vehicle state makes the mission hold and resume within tenths of a second, handing
    the same waypoints over again as a new stretch from the current one (an empty message while it
    holds): the path being flown goes on where its reference stood, not anew from rest (which
    braked the vehicle from full speed); after a hold of RESUME_S or more, or for other waypoints,
    it is made anew from the vehicle."""
    from aeroperception.services.planner.tracking import RESUME_S
    goals = [np.array(p, float) for p in SURVEY]
    for hold_s, resumes in ((0.3, True), (RESUME_S + 0.5, False)):
        tr = tracker()
        t, pos = 0.0, np.array([0.0, 0.0, 5.0])
        tr.offer(smooth_msg(), t)
        while t < 3.0:                                  # cruising towards goal 0 (10, 0, 5)
            fs = tr.step(pos, 0.0, t, goals[0])
            pos, t = fs.reference.position_m, t + DT
        speed = float(np.hypot(*fs.setpoint.velocity_mps.to_array()[:2]))
        assert speed > 1.5
        assert tr.step(pos, 0.0, t, pos) is None          # a hold goal: off the trajectory
        tr.offer(Trajectory(), t)                          # ... and no trajectory while holding
        t += hold_s
        tr.offer(smooth_msg(tid="survey_01@0b"), t)        # the same way again (here from the same waypoint)
        fs = tr.step(pos, 0.0, t, goals[0])
        again = float(np.hypot(*fs.setpoint.velocity_mps.to_array()[:2]))
        assert (tr.resumed, tr.built) == ((1, 1) if resumes else (0, 2))
        assert (again > 1.5) if resumes else (again < 0.1), again
    tr = tracker()                                        # handed over again from the next waypoint on
    t, pos = 0.0, np.array([0.0, 0.0, 5.0])
    tr.offer(smooth_msg(), t)
    while np.linalg.norm(pos - goals[0]) > 0.3:
        pos, t = tr.step(pos, 0.0, t, goals[0]).reference.position_m, t + DT
    for _ in range(25):
        pos, t = tr.step(pos, 0.0, t, goals[1]).reference.position_m, t + DT
    tr.offer(Trajectory(), t)
    tr.offer(smooth_msg(SURVEY[1:], tid="survey_01@1"), t + 0.2)
    fs = tr.step(pos, 0.0, t + 0.2, goals[1])
    assert tr.resumed == 1 and tr.first_index == -1 and float(np.hypot(*fs.setpoint.velocity_mps.to_array()[:2])) > 1.0
    t, reached = fly(tr, pos, SURVEY[1:])
    assert len(reached) == 2 and tr.built == 1             # on to the end on the same path
    tr = tracker()                                        # other waypoints: never the old path
    tr.offer(smooth_msg(), 0.0)
    tr.step(np.array([0.0, 0.0, 5.0]), 0.0, 0.0, goals[0])
    tr.offer(smooth_msg([(0, 10, 5), (10, 10, 5)], tid="other@0"), 0.1)
    tr.step(np.array([0.0, 0.0, 5.0]), 0.0, 0.2, np.array([0.0, 10.0, 5.0]))
    assert (tr.resumed, tr.built) == (0, 2)


def test_a_late_count_does_not_stop_the_reference_a_missed_waypoint_does():
    """The mission counts a waypoint by the vehicle's distance and hands the next goal over a
    message later (0.5 s after the count on a loaded host): a vehicle that reached the waypoint is
    not braked to a stop there while the count is late (for up to COUNT_GRACE_S); one that never
    came within acceptance_radius_m of it is held there, as before."""
    from aeroperception.services.planner.tracking import COUNT_GRACE_S
    goals = [np.array(p, float) for p in SURVEY]
    for reached_it in (True, False):
        tr = tracker(radius=0.5)
        tr.offer(smooth_msg())
        t, pos = 0.0, np.array([0.0, 0.0, 5.0])
        tr.step(pos, 0.0, t, goals[0])
        t_corner = tr.follower.path.waypoint_times_s[1]
        speeds = []
        while t < t_corner + 0.5:                  # the mission never moves on from goal 0 here
            t += DT
            fs = tr.step(pos, 0.0, t, goals[0])
            # the vehicle on the reference, or 0.8 m to its side (never within 0.5 m of the corner)
            pos = fs.reference.position_m if reached_it else fs.reference.position_m + np.array([0.0, -0.8, 0.0])
            speeds.append(float(np.hypot(*fs.setpoint.velocity_mps.to_array()[:2])))
        if reached_it:
            assert min(speeds[-30:]) > 0.5 and tr.late_counts == 1          # ran on through the corner
            while t < t_corner + COUNT_GRACE_S + 0.2:                         # still not counted: back to wait
                t += DT
                fs = tr.step(pos, 0.0, t, goals[0])
            assert np.allclose(fs.reference.position_m, goals[0]) and fs.setpoint.velocity_mps.to_array() == pytest.approx(0)
        else:
            assert speeds[-1] == 0.0 and tr.late_counts == 0                  # held at the waypoint


def test_a_path_starts_at_the_velocity_last_sent_unless_the_stream_broke():
    sent, own, period = np.array([0.0, 0.0, 0.27]), np.array([0.1, -0.05, 0.2]), 0.02
    # unbroken: the reference goes on from what was sent (a climbing take-off is not braked first)
    assert np.array_equal(start_velocity_mps(sent, 0.02, period, own), sent)
    assert np.array_equal(start_velocity_mps(sent, 0.059, period, own), sent)
    # broken for 3 periods or more (a stall, a planner restart): the vehicle's own velocity
    assert np.array_equal(start_velocity_mps(sent, 0.06, period, own), own)
    assert np.array_equal(start_velocity_mps(sent, 5.0, period, own), own)
    # nothing sent yet, or the last setpoint had no velocity: the vehicle's own
    assert np.array_equal(start_velocity_mps(None, 0.0, period, own), own)
