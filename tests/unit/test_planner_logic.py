"""WaypointPlanner (services/planner/logic.py): requirement PLAN-1's P-controller on position error,
velocity = direction * min(max_velocity, kp * distance), one `reached` per goal, hold without one."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import TrajectoryStatus
from aeroperception.services.planner.logic import (
    Goal, GoalWatchdog, Progress, WaypointPlanner, hold_setpoint, time_to_go_s, tracking_errors,
)


def vel(result) -> np.ndarray:
    return result.setpoint.velocity_mps.to_array()


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.0, -1.0, 0.0), (1.0, 1.0, 0.5), (-0.3, 0.4, -1.2),
                                    (1.5, -0.8, 0.1)])
def test_velocity_points_at_the_goal_with_magnitude_min_of_cap_and_kp_distance(offset):
    planner = WaypointPlanner(max_velocity_mps=2.0, kp=0.8, acceptance_radius_m=0.1)
    here = np.array([3.0, -2.0, 5.0])
    goal = here + np.array(offset)
    planner.set_goal(Goal(goal, 0.3))
    res = planner.step(here, 0.0)

    d = float(np.linalg.norm(offset))
    v = vel(res)
    assert res.distance_m == pytest.approx(d)
    assert np.linalg.norm(v) == pytest.approx(min(2.0, 0.8 * d))
    np.testing.assert_allclose(v / np.linalg.norm(v), np.array(offset) / d, atol=1e-12)
    sp = res.setpoint
    assert sp.velocity_valid and not sp.position_valid    # velocity is the command
    np.testing.assert_allclose(sp.position_m.to_array(), goal)  # position is feed-forward only
    assert sp.yaw_valid and sp.yaw_rad == pytest.approx(0.3)


def test_speed_is_capped_at_two_metres_per_second_far_away():
    planner = WaypointPlanner()
    planner.set_goal(Goal(np.array([100.0, 50.0, 10.0]), None))
    res = planner.step(np.zeros(3), 0.7)
    assert np.linalg.norm(vel(res)) == pytest.approx(2.0)
    assert res.setpoint.yaw_rad == pytest.approx(0.7)      # no goal yaw: keep the current one
    assert planner.status == TrajectoryStatus.STATUS_EXECUTING


def test_speed_ramps_down_near_the_goal():
    planner = WaypointPlanner()
    planner.set_goal(Goal(np.array([1.0, 0.0, 0.0]), None))
    speeds = [np.linalg.norm(vel(planner.step(np.array([x, 0.0, 0.0]), 0.0))) for x in (-5, -1, 0, 0.5, 0.9)]
    assert speeds == pytest.approx([2.0, 1.6, 0.8, 0.4, 0.08])


def test_reached_fires_once_per_goal_inside_the_acceptance_radius():
    planner = WaypointPlanner(acceptance_radius_m=0.5)
    planner.set_goal(Goal(np.array([10.0, 0.0, 5.0]), 0.0, index=1))
    xs = [8.0, 9.0, 9.49, 9.6, 9.8, 10.0, 9.7]
    fired = [planner.step(np.array([x, 0.0, 5.0]), 0.0).reached for x in xs]
    assert fired == [False, False, False, True, False, False, False]
    assert planner.status == TrajectoryStatus.STATUS_COMPLETED


def test_the_same_goal_sent_again_does_not_fire_reached_again():
    planner = WaypointPlanner()
    goal = np.array([1.0, 2.0, 3.0])
    planner.set_goal(Goal(goal, 0.0, index=4))
    assert planner.step(goal, 0.0).reached
    planner.set_goal(Goal(goal.copy(), 0.0, index=4))     # republished, unchanged
    assert not planner.step(goal, 0.0).reached


def test_a_new_goal_resets_reached():
    planner = WaypointPlanner()
    a, b = np.array([0.0, 0.0, 5.0]), np.array([10.0, 0.0, 5.0])
    planner.set_goal(Goal(a, 0.0, index=0))
    assert planner.step(a, 0.0).reached
    planner.set_goal(Goal(b, 0.0, index=1))
    assert planner.status == TrajectoryStatus.STATUS_EXECUTING  # at once, not at the next step
    res = planner.step(a, 0.0)
    assert not res.reached and planner.status == TrajectoryStatus.STATUS_EXECUTING
    assert planner.step(b + 0.1, 0.0).reached


def test_same_position_with_a_new_index_is_a_new_goal():
    # the last survey waypoint is the first one again: it must fire again
    planner = WaypointPlanner()
    p = np.array([0.0, 0.0, 5.0])
    planner.set_goal(Goal(p, 0.0, index=0))
    assert planner.step(p, 0.0).reached
    planner.set_goal(Goal(p.copy(), 0.0, index=3))
    assert planner.step(p, 0.0).reached


def test_holding_without_a_goal_is_a_position_setpoint_at_the_captured_point_with_zero_velocity():
    planner = WaypointPlanner()
    captured = np.array([2.0, -1.0, 4.0])
    first = planner.step(captured, 0.25)
    later = planner.step(captured + np.array([0.4, 0.3, -0.2]), 1.0)  # drifted: still the same target
    for res in (first, later):
        sp = res.setpoint
        assert sp.position_valid and sp.velocity_valid and sp.yaw_valid
        np.testing.assert_allclose(sp.position_m.to_array(), captured)
        np.testing.assert_array_equal(sp.velocity_mps.to_array(), np.zeros(3))
        assert sp.yaw_rad == pytest.approx(0.25)
        assert res.distance_m is None and not res.reached
    assert planner.status == TrajectoryStatus.STATUS_PAUSED


def test_clearing_the_goal_captures_a_new_hold_point():
    planner = WaypointPlanner()
    planner.step(np.zeros(3), 0.0)                          # hold at the origin
    planner.set_goal(Goal(np.array([5.0, 0.0, 0.0]), None))
    planner.step(np.array([2.0, 0.0, 0.0]), 0.0)
    planner.set_goal(None)
    res = planner.step(np.array([2.5, 0.0, 0.0]), math.pi / 2)
    np.testing.assert_allclose(res.setpoint.position_m.to_array(), [2.5, 0.0, 0.0])
    assert res.setpoint.yaw_rad == pytest.approx(math.pi / 2)


def test_at_the_goal_exactly_the_velocity_is_zero_not_nan():
    planner = WaypointPlanner()
    p = np.array([1.0, 1.0, 1.0])
    planner.set_goal(Goal(p, None))
    v = vel(planner.step(p.copy(), 0.0))
    assert np.all(np.isfinite(v)) and np.linalg.norm(v) == 0.0


def test_hold_setpoint_helper():
    sp = hold_setpoint(np.array([1.0, 2.0, 3.0]), -0.5)
    assert sp.position_valid and sp.velocity_valid and sp.yaw_valid
    assert not sp.acceleration_valid and not sp.yaw_rate_valid
    np.testing.assert_allclose(sp.position_m.to_array(), [1.0, 2.0, 3.0])
    assert sp.velocity_mps.to_array().tolist() == [0.0, 0.0, 0.0] and sp.yaw_rad == -0.5


def test_goal_watchdog_fires_once_when_the_mission_goes_silent_while_tracking():
    w = GoalWatchdog(2.0)
    assert not w.expired(100.0, tracking=True)           # nothing heard yet: no verdict
    assert not w.heard(100.0)
    assert not w.expired(101.9, tracking=True)
    assert not w.expired(103.0, tracking=False)          # holding already: nothing to stop
    assert w.expired(102.1, tracking=True) and w.silent
    assert not w.expired(102.2, tracking=True)           # once
    assert w.heard(105.0) and not w.silent               # the mission is back
    assert not w.expired(106.0, tracking=True)
    off = GoalWatchdog(0.0)
    off.heard(0.0)
    assert not off.expired(1e6, tracking=True)


# ---------------------------------------------------------------- planner/status progress fields

def fly_p_law(distance_m: float, vmax: float, kp: float, radius: float, dt: float = 1e-3) -> float:
    """Time the P law min(vmax, kp d), followed exactly, takes from distance_m to the radius."""
    d, t = distance_m, 0.0
    while d >= radius:
        d -= min(vmax, kp * d) * dt
        t += dt
    return t


@pytest.mark.parametrize("distance", [0.3, 0.5, 1.0, 2.5, 6.0, 40.0])
def test_time_to_go_is_the_p_laws_own_flight_time(distance):
    expected = fly_p_law(distance, 2.0, 0.8, 0.5) if distance > 0.5 else 0.0
    assert time_to_go_s(distance, 2.0, 0.8, 0.5) == pytest.approx(expected, abs=5e-3)


def test_progress_runs_from_where_the_goal_began_to_arrival_then_freezes():
    planner = WaypointPlanner(max_velocity_mps=2.0, kp=0.8, acceptance_radius_m=0.5)
    start, goal = np.array([0.0, 0.0, 5.0]), np.array([10.0, 0.0, 5.0])
    planner.set_goal(Goal(goal, None, index=1))
    planner.step(start, 0.0, now_s=100.0)
    p = planner.progress(start, 100.0)
    assert (p.percent, p.elapsed_s) == (0.0, 0.0)
    assert p.remaining_s == pytest.approx(time_to_go_s(10.0, 2.0, 0.8, 0.5))
    here = np.array([4.0, 0.0, 5.0])
    planner.step(here, 0.0, now_s=103.0)
    p = planner.progress(here, 103.0)
    assert p.percent == pytest.approx(100 * 4.0 / 9.5)        # 4 of the 9.5 m to the acceptance radius
    assert p.elapsed_s == pytest.approx(3.0)
    assert p.remaining_s == pytest.approx(time_to_go_s(6.0, 2.0, 0.8, 0.5))
    behind = np.array([-3.0, 0.0, 5.0])                        # pushed back past the start: not negative
    assert planner.progress(behind, 104.0).percent == 0.0
    arrived = np.array([9.6, 0.0, 5.0])
    assert planner.step(arrived, 0.0, now_s=106.5).reached
    later = planner.progress(goal, 200.0)
    assert (later.percent, later.elapsed_s, later.remaining_s) == (100.0, pytest.approx(6.5), 0.0)


def test_the_same_goal_again_keeps_its_leg_and_a_new_goal_or_a_hold_starts_over():
    planner = WaypointPlanner()
    planner.set_goal(Goal(np.array([10.0, 0.0, 5.0]), None, index=1))
    planner.step(np.array([0.0, 0.0, 5.0]), 0.0, now_s=1.0)
    planner.set_goal(Goal(np.array([10.0, 0.0, 5.0]), None, index=1))   # re-sent at 2 Hz
    planner.step(np.array([2.0, 0.0, 5.0]), 0.0, now_s=2.0)
    assert planner.progress(np.array([2.0, 0.0, 5.0]), 2.0).elapsed_s == pytest.approx(1.0)
    planner.set_goal(Goal(np.array([2.0, 8.0, 5.0]), None, index=2))
    planner.step(np.array([2.0, 0.0, 5.0]), 0.0, now_s=3.0)
    p = planner.progress(np.array([2.0, 0.0, 5.0]), 3.0)
    assert (p.percent, p.elapsed_s) == (0.0, 0.0)
    planner.set_goal(None)
    planner.step(np.array([2.0, 0.0, 5.0]), 0.0, now_s=4.0)
    assert planner.progress(np.array([2.0, 0.0, 5.0]), 4.0) == Progress()


def test_tracking_errors_are_against_the_goal_and_the_velocity_sent():
    planner = WaypointPlanner()
    planner.set_goal(Goal(np.array([10.0, 0.0, 5.0]), None))
    res = planner.step(np.array([0.0, 0.0, 5.0]), 0.0)            # commands 2 m/s east
    pos_err, vel_err = tracking_errors(res.setpoint, planner, np.array([0.0, 0.0, 5.0]), np.array([0.5, 0.0, 0.0]))
    assert (pos_err, vel_err) == (pytest.approx(10.0), pytest.approx(1.5))
    planner.set_goal(None)
    hold = planner.step(np.array([1.0, 1.0, 5.0]), 0.0)
    pos_err, vel_err = tracking_errors(hold.setpoint, planner, np.array([1.0, 1.3, 5.0]), np.array([0.0, 0.3, 0.4]))
    assert (pos_err, vel_err) == (pytest.approx(0.3), pytest.approx(0.5))


def test_a_goals_own_speed_caps_limit_the_command():
    """mission/active_goal's max_speed_mps (a goto's velocity_mps) and max_vertical_speed_mps (a
    takeoff's climb / a landing's descent rate) cap the velocity, on the same straight line."""
    from aeroperception.services.planner.logic import Goal, WaypointPlanner

    p = WaypointPlanner(max_velocity_mps=2.0, kp=0.8)
    p.set_goal(Goal(np.array([10.0, 0.0, 0.0]), None, 1, max_speed_mps=0.7))
    v = p.step(np.zeros(3), 0.0).setpoint.velocity_mps.to_array()
    np.testing.assert_allclose(v, [0.7, 0.0, 0.0])
    p.set_goal(Goal(np.array([0.0, 0.0, 5.0]), None, 2, max_vertical_speed_mps=0.5))
    np.testing.assert_allclose(p.step(np.zeros(3), 0.0).setpoint.velocity_mps.to_array(), [0.0, 0.0, 0.5])
    p.set_goal(Goal(np.array([4.0, 0.0, -4.0]), None, 3, max_vertical_speed_mps=0.5))
    v = p.step(np.zeros(3), 0.0).setpoint.velocity_mps.to_array()
    np.testing.assert_allclose(v, [0.5, 0.0, -0.5])           # direction kept, vertical part capped
    p.set_goal(Goal(np.array([0.0, 0.0, 5.0]), None, 4))
    np.testing.assert_allclose(p.step(np.zeros(3), 0.0).setpoint.velocity_mps.to_array(), [0.0, 0.0, 2.0])


def test_remaining_time_is_at_the_goals_own_speed_caps():
    planner = WaypointPlanner(max_velocity_mps=2.0, kp=0.8, acceptance_radius_m=0.5)
    planner.set_goal(Goal(np.array([10.0, 0.0, 5.0]), None, max_speed_mps=0.6))
    planner.step(np.array([0.0, 0.0, 5.0]), 0.0, now_s=0.0)
    assert planner.progress(np.array([0.0, 0.0, 5.0]), 0.0).remaining_s == pytest.approx(time_to_go_s(10.0, 0.6, 0.8, 0.5))
    planner.set_goal(Goal(np.array([0.0, 0.0, 1.0]), None, index=2, max_vertical_speed_mps=0.5))   # 4 m down
    planner.step(np.array([0.0, 0.0, 5.0]), 0.0, now_s=1.0)
    assert planner.progress(np.array([0.0, 0.0, 5.0]), 1.0).remaining_s == pytest.approx(time_to_go_s(4.0, 0.5, 0.8, 0.5))


def test_a_hold_is_retaken_where_the_vehicle_is_after_the_fc_flew_on_its_own():
    """PX4's offboard-loss failsafe (RTL) moves the vehicle while we hold; once setpoints flow again
    PX4 returns to OFFBOARD by itself: the hold must be where the vehicle is then, not flown back to."""
    planner = WaypointPlanner()
    planner.step(np.zeros(3), 0.0)                          # holding at the origin
    planner.retake_hold()                                   # the FC flew RTL meanwhile
    res = planner.step(np.array([3.0, 1.0, 6.0]), 0.5)
    np.testing.assert_allclose(res.setpoint.position_m.to_array(), [3.0, 1.0, 6.0])
    assert res.setpoint.yaw_rad == pytest.approx(0.5)
    planner.set_goal(Goal(np.array([9.0, 0.0, 5.0]), None))  # a goal is never dropped by it
    planner.retake_hold()
    assert planner.step(np.zeros(3), 0.0).distance_m == pytest.approx(np.hypot(9.0, 5.0))


def test_a_new_goal_after_a_completed_one_reads_executing_with_its_time_to_go_before_its_first_step():
    """planner/status runs on its own 10 Hz timer: between a new goal and the next 50 Hz step it
    showed the last goal's COMPLETED and a remaining time of 0 under the new goal's id."""
    planner = WaypointPlanner(max_velocity_mps=2.0, kp=0.8, acceptance_radius_m=0.5)
    here = np.array([0.0, 0.0, 5.0])
    planner.set_goal(Goal(here, None, index=1))
    planner.step(here, 0.0, now_s=1.0)
    assert planner.status == TrajectoryStatus.STATUS_COMPLETED
    planner.set_goal(Goal(np.array([-8.0, 0.0, 5.0]), None, index=2))
    assert planner.status == TrajectoryStatus.STATUS_EXECUTING
    p = planner.progress(here, 2.0)
    assert (p.percent, p.elapsed_s) == (0.0, 0.0)
    assert p.remaining_s == pytest.approx(time_to_go_s(8.0, 2.0, 0.8, 0.5))
