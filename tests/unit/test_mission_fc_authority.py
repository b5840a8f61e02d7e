"""The flight controller has the last word: when it leaves the mode the mission asked for (a
failsafe, a pilot, another ground station) the mission holds and never takes control back by
itself; START asks again and answers with the FC's verdict.
"""
from __future__ import annotations

import pytest

from aeroperception.schemas import LandedState
from aeroperception.services.mission.fsm import Event, State
from mission_rig import SURVEY_WPS, FakeBridge, Rig, assert_goal, assert_hold, fc, vehicle


def test_fc_leaving_offboard_while_executing_holds_and_start_asks_offboard_again():
    rig = Rig()
    rig.to_executing()
    rig.feed(fc(0.0, 0.0, 5.0))                       # OFFBOARD confirmed; waypoint 0 reached
    rig.feed(fc(4.0, 0.0, 5.0))
    rig.clear()

    rig.feed(fc(4.5, 0.0, 5.0, mode="HOLD"))          # failsafe / pilot / another GCS
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.EXECUTING, Event.FC_MODE_CHANGED, State.HOLDING)
    assert "flight controller switched to HOLD" in rig.mgr.status().message
    assert_hold(rig.goals[-1]) and rig.bridge.calls == []   # stops commanding, never fights it
    rig.feed(fc(10.0, 0.0, 5.0, mode="HOLD"))         # nothing progresses while held
    assert rig.mgr.reached_events == [0] and rig.mgr.state == State.HOLDING

    ok, msg = rig.mgr.command("START")                 # resume only on command
    assert ok, msg
    assert rig.mgr.state == State.EXECUTING and rig.bridge.modes() == ["OFFBOARD"]
    assert_goal(rig.goals[-1], SURVEY_WPS[1])          # the same waypoint
    rig.feed(fc(4.5, 0.0, 5.0, mode="HOLD"))          # heartbeat lag: not yet confirmed, no false alarm
    assert rig.mgr.state == State.EXECUTING


def test_fc_mode_change_during_takeoff_holds():
    rig = Rig()
    rig.to_takeoff()
    rig.feed(fc(z=1.0))
    rig.feed(fc(z=1.5, mode="POSCTL"))
    assert rig.mgr.state == State.HOLDING and "switched to POSCTL" in rig.mgr.message


def test_fc_mode_before_our_request_is_confirmed_is_not_a_takeover():
    rig = Rig()
    rig.to_takeoff()
    rig.feed(fc(z=0.5, mode="HOLD"))                  # OFFBOARD asked, not yet in effect
    assert rig.mgr.state == State.TAKEOFF


def test_pilot_taking_over_a_landing_holds_without_taking_control_back():
    rig = Rig()
    rig.to_executing()
    rig.feed(fc())
    rig.mgr.command("LAND")
    rig.feed(fc(mode="OFFBOARD"))                     # LAND not yet confirmed: no verdict
    assert rig.mgr.state == State.LAND
    rig.feed(fc(z=4.0, mode="LAND"))
    rig.clear()
    rig.feed(fc(z=3.5, mode="POSCTL"))
    assert rig.mgr.state == State.HOLDING and "switched to POSCTL" in rig.mgr.message
    assert rig.bridge.calls == []


def test_rtl_landing_is_not_mistaken_for_a_takeover():
    rig = Rig()
    rig.to_executing()
    rig.mgr.command("RTL")
    for mode in ("RTL", "LAND", "RTL"):               # an autopilot may report its land phase as LAND
        rig.feed(fc(mode=mode))
    assert rig.mgr.state == State.LAND


def test_fc_mode_change_while_holding_is_reported_and_start_resumes():
    rig = Rig()
    rig.to_holding()
    rig.feed(fc())
    rig.feed(fc(mode="HOLD"))
    assert rig.mgr.state == State.HOLDING and "switched to HOLD" in rig.mgr.message
    rig.mgr.command("START")
    assert rig.bridge.modes()[-1] == "OFFBOARD" and rig.mgr.state == State.EXECUTING


def test_offboard_refused_when_resuming_stays_holding_with_the_reason():
    rig = Rig()
    rig.to_executing()
    rig.feed(fc())
    rig.feed(fc(mode="HOLD"))
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "denied by pilot"
    ok, msg = rig.mgr.command("START")
    assert not ok and "denied by pilot" in msg
    assert rig.mgr.state == State.HOLDING


@pytest.mark.parametrize("src", [State.TAKEOFF, State.EXECUTING, State.HOLDING])
def test_fc_landed_and_disarmed_on_its_own_goes_idle_with_the_mission_kept(src):
    rig = Rig()
    rig.to(src)
    rig.feed(fc(z=2.0, mode="LAND"))
    rig.feed(fc(z=0.0, mode="LAND", armed=False, landed=LandedState.ON_GROUND))
    assert rig.mgr.state == State.IDLE
    assert rig.mgr.transitions[-1] == (src, Event.FC_LANDED, State.IDLE)
    assert "landed and disarmed on its own" in rig.mgr.status().message
    assert rig.mgr.mission is not None


def test_takeoff_is_not_ended_by_a_disarmed_state_from_before_arming():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.bridge.answer_pending()                       # armed per the FC's ACK -> TAKEOFF
    rig.feed(vehicle())                               # state/vehicle not yet showing armed
    assert rig.mgr.state == State.TAKEOFF


def test_start_after_a_takeover_answers_with_the_fcs_offboard_outcome():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.bridge.answer_pending()                       # arm
    rig.bridge.answer_pending()                       # OFFBOARD
    rig.feed(fc())                                    # at 5 m in OFFBOARD: HOLDING
    rig.mgr.command("START")
    rig.feed(fc(mode="HOLD"))                         # a pilot/GCS took it: HOLDING
    rig.outcomes.clear()

    accepted, _ = rig.mgr.command("START", rig.outcome())
    assert accepted and rig.results == []             # not "started" before the FC said so
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "RC override"
    rig.bridge.answer_pending()
    assert rig.results == [(False, "OFFBOARD failed: RC override")]
    assert rig.mgr.state == State.HOLDING

    del rig.bridge.fail[("set_mode", "OFFBOARD")]
    rig.mgr.command("START", rig.outcome())
    rig.bridge.answer_pending()
    assert rig.results[-1][0] is True and rig.mgr.state == State.EXECUTING


def test_px4_back_in_offboard_as_it_disarms_after_landing_is_a_landing_not_a_takeover():
    """PX4 (UserModeIntention::onDisarm) switches to the last mode it can arm in when it disarms:
    after our LAND that is OFFBOARD, reported in the same heartbeat as the disarm."""
    rig = Rig()
    rig.to_executing()
    rig.feed(fc())
    rig.mgr.command("LAND")
    rig.feed(fc(z=2.0, mode="LAND"))                  # LAND confirmed
    rig.feed(fc(z=0.0, mode="LAND", landed=LandedState.ON_GROUND))
    rig.feed(fc(z=0.0, mode="OFFBOARD", armed=False, landed=LandedState.ON_GROUND))
    assert rig.mgr.transitions[-1] == (State.LAND, Event.LANDED, State.IDLE)
    assert rig.mgr.status().message == "landed and disarmed"
