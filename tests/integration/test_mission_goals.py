"""The mission against the real flight stack (sim, fmu, planner, mission, diagnostics as
separate processes; MAVLink on free UDP ports, Zenoh on a free loopback port), judged from the
sim's truth (sim/truth/state) and the real state file:

- issue 18 #9: a finished flight leaves nothing to restore; a restarted mission service on the
  ground comes up with no mission (and one killed after completing its waypoints never
  reports "waypoint 5/4").
"""
from __future__ import annotations

import json
import time

import pytest

from aerotest import wait_until
from aeroperception.schemas import MissionStatus
from test_flight import flight_stack, latest, truth
from test_mission_faults import command, ensure_landed, kill9, load, wait_status

SHORT = {"mission_id": "short_hop", "takeoff_altitude_m": 2.5,
         "waypoints": [{"x": 2.0, "y": 0.0, "z": 2.5}], "waypoint_acceptance_radius_m": 0.5}


@pytest.fixture(scope="module")
def gstack(stack_module):
    st = flight_stack(stack_module)
    st.state_file = st.log_dir / "state" / "default" / "mission.json"   # aerotest.Stack's AERO_STATE_DIR
    return st


def restart_mission(st) -> MissionStatus:
    """kill -9 the mission service; aero up restarts it; its first rebuilt status."""
    old = kill9(st, "mission")
    wait_until(lambda: st.pids().get("mission") not in (None, old), 20, "aero up restarted mission")
    return wait_status(st, lambda m: "restarted on the ground" in m.message, 20, "restarted mission rebuilt")


def test_a_finished_flight_is_not_restored_after_a_restart(gstack):
    st = gstack
    ensure_landed(st)
    r = load(st, json.dumps(SHORT))
    assert r.success, r.message
    for cmd in ("TAKEOFF", "START"):
        r = command(st, cmd)
        assert r.success, f"{cmd}: {r.message}"
    wait_status(st, lambda m: m.state == "EXECUTING", 30, "short hop EXECUTING")
    persisted = json.loads(st.state_file.read_text())
    assert persisted["mission_json"] and persisted["state"] == "EXECUTING", persisted   # in flight: kept
    wait_status(st, lambda m: m.state == "LAND", 30, "short hop complete: LAND")
    ensure_landed(st)
    persisted = json.loads(st.state_file.read_text())
    assert persisted["state"] == "IDLE" and persisted["mission_json"] is None, persisted

    s = restart_mission(st)
    print(f"after a finished flight: {s.message}")
    assert s.mission_id == "" and s.total_waypoints == 0 and s.active_waypoint == -1, s
    assert "no mission loaded" in s.message, s.message

    # The file an earlier version left after a finished flight (every waypoint done, IDLE):
    # the defect reported "mission survey_01 loaded at waypoint 5/4" and reloaded it.
    survey = {"mission_id": "survey_01", "takeoff_altitude_m": 5.0, "waypoint_acceptance_radius_m": 0.5,
              "waypoints": [{"x": 0.0, "y": 0.0, "z": 5.0}, {"x": 10.0, "y": 0.0, "z": 5.0},
                            {"x": 10.0, "y": 10.0, "z": 5.0}, {"x": 0.0, "y": 0.0, "z": 5.0}]}
    st.state_file.write_text(json.dumps({"version": 1, "mission_json": json.dumps(survey), "wp_index": 4,
                                         "state": "IDLE", "start_requested": False}))
    s = restart_mission(st)
    print(f"after an old finished snapshot: {s.message}")
    assert "5/4" not in s.message and "was complete (4/4 waypoints)" in s.message, s.message
    assert s.mission_id == "" and s.active_waypoint == -1, s
    assert not truth(st).armed and latest(st, "mission/status", MissionStatus, 2.0).state == "IDLE"
