"""A mission service restarted mid-flight: the persisted mission and progress come back, the
first vehicle state decides the FSM state, commands wait a bounded time, a finished or corrupt
mission is never resumed.
"""
from __future__ import annotations

import pytest

from aeroperception.schemas import LandedState, VehicleState, Vector3, parse_mission
from aeroperception.services.mission.fsm import Config, Event, State
from mission_rig import SURVEY_WPS, Rig, assert_goal, assert_hold, flying, restarted, snapshot_mid_survey, vehicle


def test_restart_in_flight_holds_with_the_reason_and_land_works():
    rig = restarted(snapshot_mid_survey())
    rig.feed(flying(6.0, 1.0, 5.0))
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions == [(State.IDLE, Event.RESTARTED_IN_AIR, State.HOLDING)]
    st = rig.mgr.status()
    assert "mission restarted in flight" in st.message and "was EXECUTING" in st.message
    assert st.mission_id == "survey_01" and st.active_waypoint == 2
    assert_hold(rig.goals[-1])
    assert rig.bridge.calls == []                     # holds without asking the FC for anything
    ok, msg = rig.mgr.command("LAND")
    assert ok, msg
    assert rig.mgr.state == State.LAND and rig.bridge.modes() == ["LAND"]
    rig.feed(vehicle(6.0, 1.0, 0.0))                  # landed and disarmed
    assert rig.mgr.state == State.IDLE and rig.mgr.mission is not None


@pytest.mark.parametrize(("cmd", "state", "mode"), [("RTL", State.LAND, "RTL"), ("HOLD", State.HOLDING, None)])
def test_restart_in_flight_accepts_rtl_and_hold(cmd, state, mode):
    rig = restarted(snapshot_mid_survey())
    rig.feed(flying(6.0, 1.0, 5.0))
    ok, msg = rig.mgr.command(cmd)
    assert ok or cmd == "HOLD", msg                   # HOLD while HOLDING: already holding
    assert rig.mgr.state == state
    assert rig.bridge.modes() == ([mode] if mode else [])


def test_restart_in_flight_start_resumes_from_the_persisted_waypoint_and_asks_offboard():
    rig = restarted(snapshot_mid_survey(wp_index=2))
    rig.feed(VehicleState(position_m=Vector3(x=6.0, y=1.0, z=5.0), armed=True, landed_state=LandedState.IN_AIR,
                          connected=True, flight_mode="HOLD"))
    assert rig.mgr.state == State.HOLDING and "flight controller in HOLD" in rig.mgr.message
    ok, msg = rig.mgr.command("START")
    assert ok and "resumed at waypoint 3/4" in msg
    assert rig.mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], SURVEY_WPS[2])
    assert rig.bridge.modes() == ["OFFBOARD"]         # the FC was not in OFFBOARD: ask again


def test_restart_on_the_ground_is_idle_with_the_mission_still_loaded():
    rig = restarted(snapshot_mid_survey(state="LAND"))
    rig.feed(vehicle())
    assert rig.mgr.state == State.IDLE and rig.mgr.transitions == []
    assert rig.mgr.mission is not None and rig.mgr.mission.mission_id == "survey_01"
    assert "restarted on the ground" in rig.mgr.message
    ok, msg = rig.mgr.command("TAKEOFF", rig.outcome())
    assert ok and rig.mgr.state == State.TAKEOFF


def test_restart_without_a_snapshot_over_a_flying_vehicle_still_holds_and_lands():
    rig = restarted(None)
    rig.feed(flying(1.0, 2.0, 5.0))
    assert rig.mgr.state == State.HOLDING and "no mission loaded" in rig.mgr.message
    assert not rig.mgr.command("START")[0]
    assert rig.mgr.command("LAND")[0] and rig.mgr.state == State.LAND


def test_restart_commands_wait_for_vehicle_state_for_a_bounded_time():
    rig = restarted(snapshot_mid_survey(), Config.from_params(restore_timeout_s=5.0))
    ok, msg = rig.mgr.command("LAND")
    assert not ok and "restarting" in msg
    rig.tick(6.0)                                     # no vehicle state within restore_timeout_s
    assert "no vehicle state yet" in rig.mgr.message
    ok, msg = rig.mgr.command("LAND")
    assert not ok and "not possible in IDLE" in msg   # ordinary IDLE rules now
    rig.feed(flying(6.0, 1.0, 5.0))                   # the state arrives late: still rebuilt
    assert rig.mgr.state == State.HOLDING


def test_restart_ignores_a_corrupt_mission_in_the_snapshot():
    rig = restarted({"mission_json": '{"waypoints": []}', "wp_index": 1, "state": "EXECUTING"})
    rig.feed(flying())
    assert rig.mgr.mission is None and rig.mgr.state == State.HOLDING


def test_every_change_is_persisted_and_a_snapshot_restores_the_progress():
    rig = Rig()
    saved: list[dict] = []
    rig.mgr.on_persist = saved.append
    rig.to_executing()
    rig.feed(flying(*SURVEY_WPS[0]))
    rig.feed(flying(*SURVEY_WPS[1]))                  # two waypoints done, flying to index 2
    assert [s["state"] for s in saved][:2] == ["IDLE", "TAKEOFF"]   # load, then the first transition
    assert saved[-1]["wp_index"] == 2 and saved[-1]["state"] == "EXECUTING"
    assert parse_mission(saved[-1]["mission_json"]) == rig.mgr.mission

    again = restarted(saved[-1])
    again.feed(flying(*SURVEY_WPS[1]))
    again.mgr.command("START")
    assert_goal(again.goals[-1], SURVEY_WPS[2])


def test_a_landed_flight_persists_no_mission_so_a_new_stack_starts_without_it():
    """Issue 18 #9: only a flight persists its mission; once landed (IDLE) the store holds none,
    while this process keeps it loaded (START again, gcs downloads)."""
    rig = Rig()
    saved: list[dict] = []
    rig.mgr.on_persist = saved.append
    rig.to_idle()
    assert saved[-1]["mission_json"] is None          # loaded on the ground: nothing to resume
    rig.mgr.command("TAKEOFF", rig.outcome())
    rig.feed(flying(z=0.5))
    assert saved[-1]["state"] == "TAKEOFF" and saved[-1]["mission_json"]
    rig.feed(flying(z=5.0))
    assert rig.mgr.command("START")[0]
    for wp in SURVEY_WPS:
        rig.feed(flying(*wp))
    assert rig.mgr.state == State.LAND and saved[-1]["wp_index"] == 4
    rig.feed(vehicle(*SURVEY_WPS[-1][:2], 0.0))       # landed and disarmed
    assert rig.mgr.state == State.IDLE and rig.mgr.mission is not None
    assert saved[-1] == {"mission_json": None, "wp_index": -1, "state": "IDLE", "start_requested": False}

    again = restarted(saved[-1])
    again.feed(vehicle())
    assert again.mgr.mission is None and again.mgr.status().active_waypoint == -1
    assert "no mission loaded" in again.mgr.message


@pytest.mark.parametrize("airborne", [False, True])
def test_a_completed_mission_is_never_restored_nor_indexed_past_its_end(airborne):
    """Issue 18 #9: 'mission survey_01 loaded at waypoint 5/4' from a finished flight."""
    rig = restarted(snapshot_mid_survey(wp_index=4, state="LAND"))   # killed during the final landing
    rig.feed(flying() if airborne else vehicle())
    assert rig.mgr.mission is None and rig.mgr.wp_index == -1
    assert "was complete (4/4 waypoints)" in rig.mgr.message and "5/4" not in rig.mgr.message
    st = rig.mgr.status()
    assert st.mission_id == "" and st.active_waypoint == -1 and st.total_waypoints == 0
    if airborne:
        assert rig.mgr.state == State.HOLDING and rig.mgr.command("LAND")[0]
