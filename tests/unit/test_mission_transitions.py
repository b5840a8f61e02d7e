"""The mission FSM's transition table (services/mission/fsm.py), entry by entry with each
state's entry side effects, and its ERROR path: a flight-controller call that fails holds in the
air and goes back to IDLE on the ground, the reason reported.
"""
from __future__ import annotations

import pytest

from aeroperception.schemas import LandedState
from aeroperception.services.mission.fsm import TRANSITIONS, Event, State
from mission_rig import SURVEY_WPS, FakeBridge, Rig, assert_goal, assert_hold, flying, vehicle


# ---------------------------------------------------------------- every table entry and its entry side effects

TABLE = sorted(TRANSITIONS.items(), key=lambda kv: (kv[0][0].value, kv[0][1].value))


@pytest.mark.parametrize(("src", "event", "dst"), [(s, e, d) for (s, e), d in TABLE],
                         ids=[f"{s.value}-{e.value}-{d.value}" for (s, e), d in TABLE])
def test_every_table_transition_reaches_its_target_with_entry_side_effects(src, event, dst):
    rig = Rig()
    rig.to(src)
    rig.clear()

    assert rig.mgr.fire(event, "test") is True
    assert rig.mgr.state == dst
    assert rig.mgr.transitions[-1] == (src, event, dst)
    assert rig.mgr.status().state == dst.value

    if dst == State.TAKEOFF:
        # climb straight up to the mission's takeoff altitude, and ask for OFFBOARD
        assert len(rig.goals) == 1
        assert_goal(rig.goals[0], [0.0, 0.0, 5.0])
        assert rig.bridge.calls == [("set_mode", "OFFBOARD")]
    elif dst == State.HOLDING:
        assert len(rig.goals) == 1
        if event == Event.ALTITUDE_REACHED:  # hold the takeoff target itself
            assert_goal(rig.goals[0], [0.0, 0.0, 5.0])
        else:
            assert_hold(rig.goals[0])  # (a finished goto holds at its target: see the goto tests)
        # leaving AUTO.LAND needs OFFBOARD back, unless a pilot took it (never fight the FC);
        # otherwise we are already in OFFBOARD
        expected = [("set_mode", "OFFBOARD")] if src == State.LAND and event != Event.FC_MODE_CHANGED else []
        assert rig.bridge.calls == expected
    elif dst == State.EXECUTING:
        assert len(rig.goals) == 1
        assert_goal(rig.goals[0], SURVEY_WPS[0], yaw=0.0)
        assert rig.bridge.calls == []
    elif dst == State.LAND:
        mode = "RTL" if event in (Event.RTL_CMD, Event.PERCEPTION_TIMEOUT, Event.SAFETY_RTH,
                                      Event.GOAL_BLOCKED_RTL) else "LAND"
        assert rig.bridge.calls == [("set_mode", mode)]
        assert rig.mgr.land_mode == mode
        assert rig.goals == []
    elif dst == State.IDLE:
        assert len(rig.goals) == 1
        assert_hold(rig.goals[0])
        assert rig.bridge.calls == []
    else:  # pragma: no cover - a new state needs its entry side effects pinned here
        pytest.fail(f"no entry expectations for {dst}")


def test_table_covers_every_state_and_event_is_used():
    assert {s for s, _ in TRANSITIONS} | set(TRANSITIONS.values()) == set(State)
    assert {e for _, e in TRANSITIONS} == set(Event)


UNLISTED = [(s, e) for s in State for e in Event if (s, e) not in TRANSITIONS]


@pytest.mark.parametrize(("src", "event"), UNLISTED, ids=[f"{s.value}-{e.value}" for s, e in UNLISTED])
def test_events_not_in_the_table_are_ignored(src, event):
    rig = Rig()
    rig.to(src)
    before = list(rig.mgr.transitions)
    rig.clear()

    assert rig.mgr.fire(event, "test") is False
    assert rig.mgr.state == src
    assert rig.mgr.transitions == before
    assert rig.goals == [] and rig.bridge.calls == []


# ---------------------------------------------------------------- failed flight-controller calls

def test_failed_land_request_in_the_air_holds_and_reports_the_reason():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF, OFFBOARD asked
    rig.bridge.answer_pending()                       # OFFBOARD ok
    rig.feed(flying(z=5.0))
    rig.mgr.command("START")
    rig.feed(flying(z=5.0))                           # waypoint 0 reached
    assert rig.mgr.state == State.EXECUTING
    rig.bridge.fail[("set_mode", "LAND")] = "mode change denied"
    rig.clear()

    rig.mgr.command("LAND")
    assert rig.mgr.state == State.LAND
    rig.bridge.answer_pending()                       # the FC says no

    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.LAND, Event.BRIDGE_FAILED_AIR, State.HOLDING)
    status = rig.mgr.status()
    assert status.state == "HOLDING"
    assert "LAND failed" in status.message and "mode change denied" in status.message
    assert_hold(rig.goals[-1])
    assert rig.bridge.modes() == ["LAND", "OFFBOARD"]  # and take control back


def test_failed_offboard_during_takeoff_in_the_air_holds():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF, OFFBOARD pending
    assert rig.mgr.state == State.TAKEOFF
    rig.feed(flying(z=1.0))                           # already off the ground
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "no setpoint stream"
    rig.bridge.answer_pending()

    assert rig.mgr.state == State.HOLDING
    assert "OFFBOARD failed: no setpoint stream" in rig.mgr.status().message


def test_failed_offboard_on_the_ground_goes_back_to_idle():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF
    rig.feed(vehicle(armed=True, landed=LandedState.ON_GROUND))
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "no setpoint stream"
    rig.goals.clear()
    rig.bridge.answer_pending()

    assert rig.mgr.state == State.IDLE
    assert rig.mgr.transitions[-1] == (State.TAKEOFF, Event.BRIDGE_FAILED_GROUND, State.IDLE)
    assert "OFFBOARD failed: no setpoint stream" in rig.mgr.status().message
    assert_hold(rig.goals[-1])


def test_failed_offboard_when_aborting_a_landing_stays_holding_and_reports():
    rig = Rig()
    rig.to_land()
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "denied"
    rig.mgr.command("HOLD")                           # LAND -> HOLDING asks for OFFBOARD: refused
    assert rig.mgr.state == State.HOLDING             # no table entry for HOLDING + failure
    assert rig.mgr.status().message == "OFFBOARD failed: denied"


def test_arm_refused_stays_idle_and_reports():
    rig = Rig()
    rig.to_idle()
    rig.bridge.fail[("arm", True)] = "preflight checks failed"

    accepted, _ = rig.mgr.command("TAKEOFF", rig.outcome())

    assert accepted  # accepted at once; the final answer settles its outcome
    assert rig.mgr.state == State.IDLE
    assert rig.bridge.calls == [("arm", True)]        # no mode request after a refused arm
    assert rig.results == [(False, "arming failed: preflight checks failed")]
    assert "preflight checks failed" in rig.mgr.status().message
    assert rig.mgr.transitions == []


def test_arm_command_refusal_is_reported_through_its_outcome():
    rig = Rig()
    rig.to_idle()
    rig.bridge.fail[("arm", True)] = "throttle not low"
    rig.mgr.command("ARM", rig.outcome())
    assert rig.results == [(False, "throttle not low")]
    assert rig.mgr.state == State.IDLE


def test_takeoff_refused_without_a_connected_vehicle():
    rig = Rig()
    rig.feed(vehicle(connected=False))
    accepted, msg = rig.mgr.command("TAKEOFF", rig.outcome())
    assert not accepted and "no vehicle state" in msg
    assert rig.bridge.calls == [] and rig.mgr.state == State.IDLE


def test_takeoff_when_already_armed_does_not_arm_again():
    rig = Rig()
    rig.to_idle()
    rig.feed(vehicle(armed=True))
    rig.mgr.command("TAKEOFF", rig.outcome())
    assert rig.bridge.calls == [("set_mode", "OFFBOARD")]
    assert rig.mgr.state == State.TAKEOFF
    assert rig.results == [(True, "taking off")]
