"""Operator commands to the mission FSM: LOAD, START, HOLD, LAND, RTL, ARM/DISARM, goto, and
SET_CURRENT (jump to a waypoint); each refused with the reason when it cannot be honoured.
"""
from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from aeroperception.schemas import LandedState, Mission, parse_mission
from aeroperception.services.mission.fsm import Event, State
from mission_rig import SURVEY_WPS, Rig, assert_goal, flying, survey, vehicle


# ---------------------------------------------------------------- operator commands

def test_mission_load_is_rejected_while_executing():
    rig = Rig()
    rig.to_executing()
    other = survey(mission_id="other", waypoints=[{"x": 1.0, "y": 1.0, "z": 2.0}])
    ok, msg = rig.mgr.load(msgspec.convert(msgspec.to_builtins(other), Mission))
    assert not ok and "EXECUTING" in msg
    assert rig.mgr.mission.mission_id == "survey_01"
    assert rig.mgr.state == State.EXECUTING


def test_mission_load_in_holding_replaces_the_mission_from_its_first_waypoint():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.mgr.command("HOLD")
    other = parse_mission('{"mission_id": "other", "waypoints": [{"x": 1, "y": 2, "z": 3}]}')
    ok, _ = rig.mgr.load(other)
    assert ok and rig.mgr.wp_index == -1
    rig.mgr.command("START")
    assert_goal(rig.goals[-1], [1.0, 2.0, 3.0])


def test_invalid_mission_json_never_reaches_the_manager():
    from aeroperception.schemas import SchemaError
    with pytest.raises(SchemaError, match="waypoints"):
        parse_mission('{"mission_id": "bad", "waypoints": []}')
    with pytest.raises(SchemaError, match=r"\$\.waypoints\[0\]\.x"):
        parse_mission('{"waypoints": [{"x": "a", "y": 0, "z": 1}]}')


def test_start_without_a_mission_is_refused():
    rig = Rig()
    rig.feed(vehicle())
    ok, msg = rig.mgr.command("START", rig.outcome())
    assert not ok and "no mission" in msg
    assert rig.results == [(False, msg)]


def test_start_from_idle_is_refused():
    rig = Rig()
    rig.to_idle()
    ok, msg = rig.mgr.command("START")
    assert not ok and "TAKEOFF first" in msg and rig.mgr.state == State.IDLE


def test_unknown_command_is_refused():
    rig = Rig()
    ok, msg = rig.mgr.command("FLIP", rig.outcome())
    assert not ok and "unknown command" in msg


def test_goto_from_holding_executes_then_holds_when_reached():
    rig = Rig()
    rig.to_holding()
    rig.clear()
    ok, _ = rig.mgr.goto(np.array([3.0, 4.0, 6.0]), 0.5)
    assert ok and rig.mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], [3.0, 4.0, 6.0], yaw=0.5)
    assert rig.mgr.distance_to_goal_m() == pytest.approx(math.sqrt(9 + 16 + 1))

    rig.feed(flying(1.5, 2.0, 5.5))
    assert rig.mgr.state == State.EXECUTING
    rig.feed(flying(2.9, 3.9, 6.0))                   # inside 0.5 m
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.EXECUTING, Event.GOTO_DONE, State.HOLDING)
    assert rig.mgr.goto_target is None
    assert_goal(rig.goals[-1], [3.0, 4.0, 6.0], yaw=0.5)  # holds at the target, not 0.5 m short
    assert rig.mgr.reached_events == []               # no mission waypoint was flown


def test_goto_needs_the_vehicle_in_the_air():
    rig = Rig()
    rig.to_idle()
    ok, msg = rig.mgr.goto(np.array([1.0, 1.0, 1.0]), None)
    assert not ok and rig.mgr.state == State.IDLE and rig.goals == []


def test_disarm_is_refused_in_the_air():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.clear()
    ok, msg = rig.mgr.command("DISARM", rig.outcome())
    assert not ok and "in the air" in msg
    assert rig.bridge.calls == []
    assert rig.results == [(False, msg)]


def test_disarm_on_the_ground_goes_to_the_bridge():
    rig = Rig()
    rig.feed(vehicle(armed=True))
    ok, _ = rig.mgr.command("DISARM", rig.outcome())
    assert ok and rig.bridge.calls == [("arm", False)]
    assert rig.results == [(True, "ok")]


def test_land_disarms_if_still_armed_on_the_ground_after_the_grace_period():
    rig = Rig()
    rig.to_land()
    rig.clear()
    rig.feed(vehicle(z=0.0, armed=True, landed=LandedState.ON_GROUND), dt=1.0)
    t0 = rig.t
    rig.feed(vehicle(armed=True), dt=4.9)             # 4.9 s on the ground
    assert rig.bridge.calls == []
    rig.feed(vehicle(armed=True), dt=0.2)             # 5.1 s > disarm_after_landing_s
    assert rig.t - t0 > rig.mgr.cfg.disarm_after_landing_s
    assert rig.bridge.calls == [("arm", False)]
    rig.feed(vehicle(armed=True), dt=1.0)             # sent once
    assert rig.bridge.calls == [("arm", False)]
    rig.feed(vehicle(armed=False))
    assert rig.mgr.state == State.IDLE


def test_land_grace_period_restarts_if_the_vehicle_bounces():
    rig = Rig()
    rig.to_land()
    rig.clear()
    rig.feed(vehicle(armed=True), dt=1.0)
    rig.feed(vehicle(armed=True), dt=4.0)
    rig.feed(vehicle(z=0.3, armed=True, landed=LandedState.IN_AIR), dt=0.5)
    rig.feed(vehicle(armed=True), dt=0.5)
    rig.feed(vehicle(armed=True), dt=4.0)
    assert rig.bridge.calls == []


def test_rtl_command_lands_through_rtl_mode_and_hold_aborts_it():
    rig = Rig()
    rig.to_executing()
    rig.clear()
    rig.mgr.command("RTL")
    assert rig.mgr.state == State.LAND and rig.bridge.calls == [("set_mode", "RTL")]
    rig.mgr.command("HOLD")
    assert rig.mgr.state == State.HOLDING
    assert rig.bridge.calls[-1] == ("set_mode", "OFFBOARD")


def test_link_loss_while_executing_holds():
    rig = Rig()
    rig.to_executing()
    rig.mgr.on_link(False)
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "link"


def test_status_reports_progress():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.feed(flying(4.0, 0.0, 5.0))
    st = rig.mgr.status()
    assert (st.mission_id, st.state, st.active_waypoint, st.total_waypoints) == ("survey_01", "EXECUTING", 1, 4)
    assert st.distance_to_goal_m == pytest.approx(6.0)
    assert st.elapsed_time_s > 0


def test_goto_uses_the_goals_own_acceptance_radius():
    rig = Rig()
    rig.to_holding()
    ok, _ = rig.mgr.goto(np.array([3.0, 4.0, 6.0]), None, acceptance_radius_m=2.0)
    assert ok and rig.mgr.state == State.EXECUTING
    rig.feed(flying(2.0, 3.0, 5.5))                   # 1.5 m away: inside 2.0, outside the mission's 0.5
    assert rig.mgr.state == State.HOLDING


# ---------------------------------------------------------------- jump to a waypoint (SET_CURRENT)

def test_set_current_while_executing_flies_to_that_waypoint_next():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(*SURVEY_WPS[0]))                  # waypoint 0 reached: flying to index 1
    assert rig.mgr.wp_index == 1
    ok, msg = rig.mgr.command("SET_CURRENT", waypoint_index=3)
    assert ok and msg == "jumped to waypoint 4/4", msg
    assert_goal(rig.goals[-1], SURVEY_WPS[3])
    assert rig.mgr.status().active_waypoint == 3
    rig.feed(flying(*SURVEY_WPS[3]))                  # reached: the mission completes, 1 and 2 skipped
    assert rig.mgr.state == State.LAND and rig.mgr.reached_events == [0, 3]


def test_set_current_while_holding_or_on_the_ground_is_where_start_goes():
    rig = Rig()
    rig.to_idle()
    ok, msg = rig.mgr.command("SET_CURRENT", waypoint_index=2)
    assert ok and "3/4 is next" in msg and rig.mgr.state == State.IDLE and rig.goals == []
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.feed(flying(z=0.5))
    rig.feed(flying(z=5.0))
    assert rig.mgr.command("START")[0]
    assert_goal(rig.goals[-1], SURVEY_WPS[2])


@pytest.mark.parametrize(("index", "words"), [(4, "out of range: the mission has 4 (0..3)"), (-1, "out of range")])
def test_set_current_out_of_range_or_without_a_mission_is_refused(index, words):
    rig = Rig()
    rig.feed(vehicle())
    assert rig.mgr.command("SET_CURRENT", waypoint_index=1) == (False, "no mission loaded; LOAD one first")
    rig.to_executing()
    ok, msg = rig.mgr.command("SET_CURRENT", waypoint_index=index)
    assert not ok and words in msg and rig.mgr.wp_index == 0


def test_set_current_command_is_decoded_strictly():
    from aeroperception.schemas import MissionCommand, SchemaError, decode, encode
    assert MissionCommand(command="set_current", waypoint_index=2).waypoint_index == 2
    with pytest.raises(ValueError, match="`waypoint_index`.*required"):
        MissionCommand(command="SET_CURRENT")
    with pytest.raises(ValueError, match="`waypoint_index` is only for SET_CURRENT"):
        MissionCommand(command="START", waypoint_index=1)
    import msgpack
    with pytest.raises(SchemaError, match="unknown field `index`"):
        decode(msgpack.packb({"command": "SET_CURRENT", "waypoint_index": 1, "index": 1}), MissionCommand, strict=True)
    assert decode(encode(MissionCommand(command="SET_CURRENT", waypoint_index=1)), MissionCommand).waypoint_index == 1
