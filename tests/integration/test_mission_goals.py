"""The mission against the real flight stack (sim, fmu, planner, mission, diagnostics as
separate processes; MAVLink on free UDP ports, Zenoh on a free loopback port), judged from the
sim's truth (sim/truth/state) and the real state file:

- a finished flight leaves nothing to restore; a restarted mission service on the
  ground comes up with no mission (and one killed after completing its waypoints never
  reports "waypoint 5/4").
- the takeoff / land / goto actions' fields are honoured, judged by the truth:
  climb and descent rate 0.5 vs 1.5 m/s give measurably different vertical speeds, a goto's
  velocity_mps caps the horizontal speed, a land at target_position_m lands there.
- the ground-station side: why the mission holds reaches ground stations as a
  STATUSTEXT, once per reason.
- MAVSDK's set_current_mission_item while the mission flies to item 1 makes the
  vehicle fly to item 3 next (truth: items 1 and 2 are never approached), as PX4 jumps.
"""
from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest

from aerotest import free_udp_port, wait_until
from aeroperception.schemas import (
    GoalStatus, GoToPositionGoal, LandGoal, LandResult, MissionStatus, TakeoffGoal, Vector3, VehicleState,
)
from aeroperception.services.runtime import ActionClient
from test_flight import flight_stack, wait_at_rest
from test_mission_faults import kill9, load, wait_status

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
    st.ensure_landed()
    r = load(st, json.dumps(SHORT))
    assert r.success, r.message
    for cmd in ("TAKEOFF", "START"):
        r = st.command(cmd)
        assert r.success, f"{cmd}: {r.message}"
    wait_status(st, lambda m: m.state == "EXECUTING", 30, "short hop EXECUTING")
    persisted = json.loads(st.state_file.read_text())
    assert persisted["mission_json"] and persisted["state"] == "EXECUTING", persisted   # in flight: kept
    wait_status(st, lambda m: m.state == "LAND", 30, "short hop complete: LAND")
    st.ensure_landed()
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
    assert not st.truth().armed and st.latest("mission/status", MissionStatus, 2.0).state == "IDLE"


def test_mavsdk_set_current_mission_item_makes_the_vehicle_jump(stack):
    pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.mission_raw.mission_raw import MissionRawAsync
    from mavsdk.plugins.mission_raw import MissionItem
    from pymavlink.dialects.v20 import common as M
    from test_gcs import HOME, mavsdk_autopilot, start_stack, waypoints

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)
    alt = 3.0
    rows = [(M.MAV_CMD_NAV_TAKEOFF, HOME.lat_deg, HOME.lon_deg, alt)] + \
        [(M.MAV_CMD_NAV_WAYPOINT, *p) for p in waypoints(n=3, alt=alt)]
    items = [MissionItem(seq=i, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=cmd, current=int(i == 0),
                         autocontinue=1, param1=0.0, param2=0.5 if cmd == M.MAV_CMD_NAV_WAYPOINT else 0.0,
                         param3=0.0, param4=float("nan"), x=round(lat * 1e7), y=round(lon * 1e7), z=z,
                         mission_type=0) for i, (cmd, lat, lon, z) in enumerate(rows)]
    enu = {i: np.array(HOME.to_enu(*rows[i][1:])) for i in (1, 2, 3)}
    jumped: dict[str, float] = {}

    def status(pred):
        m = st.latest("mission/status", MissionStatus, 1.0, pred)
        return m

    async def session():
        async with mavsdk_autopilot(sdk_port) as system:
            raw, action = MissionRawAsync(system), ActionAsync(system)
            await asyncio.wait_for(raw.upload_mission(items), 20)
            await asyncio.wait_for(action.arm(), 15)
            await asyncio.wait_for(raw.start_mission(), 15)
            await asyncio.to_thread(wait_until, lambda: status(
                lambda m: m.state == "EXECUTING" and m.active_waypoint == 0 and (m.distance_to_goal_m or 0) > 2.5),
                40, "flying to item 1 (waypoint 0)")
            await asyncio.wait_for(raw.set_current_mission_item(3), 10)
            jumped["at"] = len(rec.get("truth"))
            s = await asyncio.to_thread(wait_until, lambda: status(lambda m: m.active_waypoint == 2), 5,
                                        "mission/status at waypoint index 2")
            jumped["message"] = s.message
            await asyncio.to_thread(wait_until, lambda: status(lambda m: m.state in ("LAND", "IDLE")), 40,
                                    "the mission completes after item 3")

    rec = st.capture(truth=("sim/truth/state", VehicleState))
    try:
        asyncio.run(asyncio.wait_for(session(), 120))
        track = np.array([m.position_m.to_array() for m in rec.get("truth")[jumped["at"]:]])
    finally:
        rec.close()
    near = {i: float(np.linalg.norm(track - p, axis=1).min()) for i, p in enu.items()}
    print(f"after the jump to item 3: closest approach per item {({i: round(d, 2) for i, d in near.items()})}; "
          f"{jumped['message']}")
    assert near[3] < 0.6, f"never reached item 3 at {enu[3]}"
    assert near[1] > 1.5 and near[2] > 1.5, f"flew on to the skipped items: {near}"


def run_goal(st, action: str, goal, timeout_s: float = 60.0) -> tuple[list[VehicleState], object]:
    """Send one mission action goal, wait for SUCCEEDED; the true states meanwhile and its result."""
    client = ActionClient(st.session, f"mission/action/{action}")
    try:
        with st.capture(truth=("sim/truth/state", VehicleState)) as rec:
            g = client.send_goal(goal)
            assert g.success, f"{action} refused: {g.message}"
            res = client.result(g.goal_id, timeout_s)
            assert res.status == GoalStatus.SUCCEEDED, f"{action}: {GoalStatus.name(res.status)} {res.message}"
            return rec.get("truth"), res
    finally:
        client.close()


def vertical_speeds(track: list[VehicleState], z_from: float, z_to: float) -> np.ndarray:
    """The true vertical speeds while the vehicle was between two heights."""
    lo, hi = sorted((z_from, z_to))
    return np.array([m.velocity_mps.z for m in track if lo < m.position_m.z < hi])


def test_takeoff_land_goto_fields_are_honoured_by_truth(gstack):
    st = gstack
    st.ensure_landed()
    slow_up, _ = run_goal(st, "takeoff", TakeoffGoal(target_altitude_m=3.0, climb_rate_mps=0.5))
    wait_at_rest(st)
    track, _ = run_goal(st, "goto", GoToPositionGoal(position_m=Vector3(x=4.0, y=0.0, z=3.0), velocity_mps=0.6))
    goto_speed = max(np.hypot(m.velocity_mps.x, m.velocity_mps.y) for m in track)
    target = np.array([0.0, 3.0])
    slow_down, res = run_goal(st, "land", LandGoal(land_at_current_position=False, descent_rate_mps=0.5,
                                                   target_position_m=Vector3(x=0.0, y=3.0, z=0.0)))
    landed_at = st.truth().position_m
    miss = float(np.hypot(landed_at.x - target[0], landed_at.y - target[1]))

    fast_up, _ = run_goal(st, "takeoff", TakeoffGoal(target_altitude_m=5.0, climb_rate_mps=1.5))
    wait_at_rest(st)
    fast_down, _ = run_goal(st, "land", LandGoal(descent_rate_mps=1.5))

    climb = {0.5: vertical_speeds(slow_up, 0.3, 2.7).max(), 1.5: vertical_speeds(fast_up, 0.3, 4.7).max()}
    descent = {0.5: -vertical_speeds(slow_down, 2.7, 1.3).min(), 1.5: -vertical_speeds(fast_down, 4.7, 1.3).min()}
    print(f"climb m/s {climb}; descent m/s {descent}; goto 0.6 m/s cap: {goto_speed:.2f} m/s; "
          f"landed {miss:.2f} m from the target {target} ({LandResult.__name__}: {res.message})")
    assert climb[0.5] < 0.65 and climb[1.5] > 1.1, climb
    assert descent[0.5] < 0.65 and descent[1.5] > 1.1, descent
    assert 0.45 < goto_speed < 0.75, goto_speed
    assert miss < 0.5 and not st.truth().armed, f"landed at {landed_at}, {miss:.2f} m from {target}"


def test_why_the_mission_holds_reaches_ground_stations_once(zenoh_router, make_node, tmp_path):
    from pymavlink.dialects.v20 import common as M
    from test_gcs_ground_stations import GcsProcess, Station

    reason = ("holding: waypoint 2/3 (5.0, 13.0, 1.5) unreachable for 5 s (planner unreachable: goal "
              "(5.0, 13.0) is inside an obstacle); START retries, SET_CURRENT skips, LAND/RTL")
    pub = make_node("test-mission").publisher("mission/status", MissionStatus)
    port = free_udp_port()
    gcs = GcsProcess(zenoh_router, tmp_path / "gcs.log", port, free_udp_port()).start()
    station = Station(port)
    station.beating.set()
    try:
        wait_until(lambda: station.messages("HEARTBEAT"), 10, "gcs heartbeats")
        t = time.monotonic()
        for state, message in [("EXECUTING", "mission started")] + [("HOLDING", reason)] * 8:
            pub.publish(MissionStatus(mission_id="face", state=state, active_waypoint=1, total_waypoints=3,
                                      message=message))
            time.sleep(0.25)

        def texts() -> list[str]:
            chunks: dict[int, list] = {}
            for m in station.messages("STATUSTEXT", since=t):
                chunks.setdefault(m.id, []).append(m)
            return ["".join(c.text for c in sorted(cs, key=lambda c: c.chunk_seq)) for cs in chunks.values()
                    if cs[0].severity == M.MAV_SEVERITY_WARNING]
        wait_until(lambda: any(reason in x for x in texts()), 5, "the STATUSTEXT with the reason")
        time.sleep(0.5)
        assert texts() == [f"Mission HOLDING: {reason}"], texts()       # once, not at every 2 Hz status
    finally:
        gcs.stop()
        station.close()
