"""Whole flights through the mission FSM: survey_01 idle to idle (alone and closed-loop with
the planner), flying a finished mission again, the takeoff holding its target, and the goal fields
(climb rate, goto speed, landing target and descent rate) reaching the planner.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.schemas import LandedState, parse_mission
from aeroperception.services.mission.fsm import Config, Event, State
from aeroperception.services.planner.logic import Goal, WaypointPlanner
from mission_rig import SURVEY_01, SURVEY_WPS, Rig, assert_goal, fc, flying, vehicle


# ---------------------------------------------------------------- nominal flight

def test_nominal_survey_01_flight_idle_to_idle():
    rig = Rig()
    mgr, bridge = rig.mgr, rig.bridge
    rig.feed(vehicle())
    ok, msg = mgr.load(parse_mission(SURVEY_01.read_text()))
    assert ok and "survey_01" in msg and "4 waypoints" in msg

    # TAKEOFF: arms through the bridge, then asks for OFFBOARD, goal straight above at 5 m
    accepted, _ = mgr.command("TAKEOFF", rig.outcome())
    assert accepted and mgr.state == State.TAKEOFF
    assert bridge.calls == [("arm", True), ("set_mode", "OFFBOARD")]
    assert rig.results == [(True, "taking off")]
    assert_goal(rig.goals[-1], [0.0, 0.0, 5.0])

    # START during the climb is remembered, not refused
    accepted, msg = mgr.command("START", rig.outcome())
    assert accepted and mgr.state == State.TAKEOFF and "when takeoff completes" in msg
    for z in (0.2, 1.5, 3.0, 4.5):
        rig.feed(vehicle(z=z, armed=True, landed=LandedState.IN_AIR))
        assert mgr.state == State.TAKEOFF
    rig.feed(flying(z=4.85))                          # within the 0.3 m tolerance
    assert mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], SURVEY_WPS[0], yaw=0.0)

    # fly the square: each waypoint fires once, as the position gets there
    path = [(0.0, 0.0, 5.0), (4.0, 0.0, 5.0), (9.7, 0.1, 5.0), (10.0, 5.0, 5.0), (10.1, 9.8, 5.0),
            (5.0, 5.0, 5.0), (0.2, -0.2, 5.0)]
    reached_after = [[0], [0], [0, 1], [0, 1], [0, 1, 2], [0, 1, 2], [0, 1, 2, 3]]
    for pos, want in zip(path, reached_after):
        rig.feed(flying(*pos))
        assert mgr.reached_events == want, pos
    assert [tuple(g.position_m) for g in rig.goals if g.position_m is not None][-4:] == SURVEY_WPS

    # mission complete -> LAND via the flight controller's LAND mode
    assert mgr.state == State.LAND
    assert bridge.calls[-1] == ("set_mode", "LAND")
    rig.feed(vehicle(z=2.0, armed=True, landed=LandedState.LANDING))
    rig.feed(vehicle(z=0.0, armed=True, landed=LandedState.ON_GROUND))
    assert mgr.state == State.LAND
    rig.feed(vehicle(z=0.0, armed=False, landed=LandedState.ON_GROUND))
    assert mgr.state == State.IDLE

    states = [mgr.transitions[0][0]] + [dst for _, _, dst in mgr.transitions]
    assert states == [State.IDLE, State.TAKEOFF, State.HOLDING, State.EXECUTING, State.LAND, State.IDLE]
    assert [e for _, e, _ in mgr.transitions] == [
        Event.TAKEOFF_CMD, Event.ALTITUDE_REACHED, Event.START_CMD, Event.WAYPOINTS_DONE, Event.LANDED]
    assert mgr.status().state == "IDLE"
    assert bridge.arms() == [True]                    # the FC disarmed itself: no disarm sent


def test_mission_can_be_flown_again_after_it_completed():
    rig = Rig()
    rig.to_executing()
    for wp in SURVEY_WPS:
        rig.feed(flying(*wp))
    assert rig.mgr.reached_events == [0, 1, 2, 3] and rig.mgr.state == State.LAND
    rig.feed(vehicle())                               # landed, disarmed
    assert rig.mgr.state == State.IDLE

    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.mgr.command("START", rig.outcome())
    rig.feed(flying(z=5.0))
    assert rig.mgr.state == State.EXECUTING
    assert rig.mgr.status().active_waypoint == 0
    assert_goal(rig.goals[-1], SURVEY_WPS[0])


def test_completed_mission_holds_when_land_on_complete_is_off_and_start_restarts_it():
    rig = Rig(Config.from_params(land_on_complete=False))
    rig.to_executing()
    for wp in SURVEY_WPS:
        rig.feed(flying(*wp))
    assert rig.mgr.state == State.HOLDING
    assert rig.bridge.modes() == ["OFFBOARD"]         # no LAND requested
    rig.mgr.command("START", rig.outcome())
    assert rig.mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], SURVEY_WPS[0])


def test_mission_and_planner_fly_survey_01_closed_loop():
    """The planner's velocity setpoints, integrated, carry the vehicle through every waypoint."""
    rig = Rig()
    planner = WaypointPlanner()
    goals_seen = 0
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.mgr.command("START", rig.outcome())
    pos, dt = np.zeros(3), 0.02
    for _ in range(20_000):
        if len(rig.goals) > goals_seen:
            g = rig.goals[-1]
            goals_seen = len(rig.goals)
            planner.set_goal(None if g.position_m is None else Goal(g.position_m, g.yaw_rad, goals_seen))
        if rig.mgr.state == State.LAND:
            break
        sp = planner.step(pos, 0.0).setpoint
        if sp.velocity_valid and not sp.position_valid:
            pos = pos + sp.velocity_mps.to_array() * dt
        rig.feed(flying(*pos), dt)
    assert rig.mgr.state == State.LAND
    assert rig.mgr.reached_events == [0, 1, 2, 3]
    assert rig.t - 100.0 < 60.0                       # ~45 m at <= 2 m/s


# ---------------------------------------------------------------- the takeoff holds its target

def test_takeoff_holds_the_target_altitude_not_where_the_tolerance_was_entered():
    rig = Rig()
    rig.to_takeoff()
    rig.feed(flying(0.1, -0.1, 4.75))                 # inside the 0.3 m tolerance of 5 m
    assert rig.mgr.state == State.HOLDING
    assert_goal(rig.goals[-1], [0.0, 0.0, 5.0])       # x, y where it took off, z = the target


def test_takeoff_hold_closed_loop_settles_on_the_target():
    rig = Rig()
    planner = WaypointPlanner()
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    pos, dt, seen = np.zeros(3), 0.02, 0
    for _ in range(1500):                             # 30 s
        if len(rig.goals) > seen:
            seen, g = len(rig.goals), rig.goals[-1]
            planner.set_goal(None if g.position_m is None else Goal(g.position_m, g.yaw_rad, seen))
        sp = planner.step(pos, 0.0).setpoint
        if not sp.position_valid:
            pos = pos + sp.velocity_mps.to_array() * dt
        rig.feed(flying(*pos), dt)
    assert rig.mgr.state == State.HOLDING
    assert abs(pos[2] - 5.0) < 0.05, pos


# ---------------------------------------------------------------- goal fields honoured

def test_takeoff_climb_rate_and_goto_speed_reach_the_planner_as_caps():
    rig = Rig()
    rig.feed(vehicle())
    assert rig.mgr.takeoff(4.0, rig.outcome(), climb_rate_mps=0.5)[0]
    rig.feed(flying(z=0.5))
    assert rig.mgr.state == State.TAKEOFF and rig.goals[-1].max_vertical_speed_mps == 0.5
    rig.feed(flying(z=4.0))
    assert rig.mgr.goto(np.array([5.0, 0.0, 4.0]), None, 0.5, velocity_mps=0.8)[0]
    assert rig.goals[-1].max_speed_mps == 0.8 and rig.goals[-1].max_vertical_speed_mps == 0.0
    assert rig.mgr.goto(np.array([5.0, 0.0, 4.0]), None, 0.5, velocity_mps=-1.0) == (
        False, "goto refused: field `velocity_mps` must be >= 0 (0 = default), got -1.0")
    assert "`climb_rate_mps`" in Rig().mgr.takeoff(3.0, climb_rate_mps=math.nan)[1]


def test_land_at_a_target_flies_there_descends_at_the_rate_then_the_fc_lands():
    rig = Rig(Config.from_params(land_handoff_altitude_m=1.0))
    rig.to_holding()                                  # at (0, 0, 5)
    ok, msg = rig.mgr.land(np.array([6.0, 2.0, 0.0]), descent_rate_mps=0.5)
    assert ok and msg == "operator LAND at (6.0, 2.0), descending at 0.5 m/s", msg
    assert rig.mgr.state == State.LAND and rig.bridge.modes() == ["OFFBOARD"]   # no FC LAND yet
    assert_goal(rig.goals[-1], [6.0, 2.0, 5.0])      # approach at the current altitude
    rig.feed(flying(3.0, 1.0, 5.0))
    assert_goal(rig.goals[-1], [6.0, 2.0, 5.0])
    rig.feed(flying(5.8, 2.1, 5.0))                   # above the target: descend, capped
    assert_goal(rig.goals[-1], [6.0, 2.0, 1.0])
    assert rig.goals[-1].max_vertical_speed_mps == 0.5
    rig.feed(flying(6.0, 2.0, 3.0))
    assert rig.bridge.modes() == ["OFFBOARD"]
    rig.feed(flying(6.0, 2.0, 1.2))                   # the handoff height: the FC lands
    assert rig.bridge.modes() == ["OFFBOARD", "LAND"] and rig.mgr.state == State.LAND
    rig.feed(fc(6.0, 2.0, 0.5, mode="OFFBOARD"))      # the FC's heartbeat lags: no mode change judged
    rig.feed(fc(6.0, 2.0, 0.0, mode="LAND", armed=False, landed=LandedState.ON_GROUND))
    assert rig.mgr.state == State.IDLE


def test_land_in_place_with_only_a_descent_rate_and_refusals():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(1.0, 0.0, 5.0))
    ok, msg = rig.mgr.land(None, descent_rate_mps=1.5)
    assert ok and rig.mgr.state == State.LAND
    assert_goal(rig.goals[-1], [1.0, 0.0, 1.0]) and rig.goals[-1].max_vertical_speed_mps == 1.5
    rig2 = Rig()
    rig2.to_holding()
    assert "`descent_rate_mps` must be >= 0" in rig2.mgr.land(None, -0.5)[1]
    assert rig2.mgr.land(np.array([1e5, 0.0, 0.0]))[1].startswith("land refused: target_position_m:")
    assert rig2.mgr.state == State.HOLDING
