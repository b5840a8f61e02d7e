"""The mission protocol kept in step with the mission service: an upload is converted and loaded
(refused before any call when its speeds are out of the planner's range), a mission loaded some
other way is fetched and served as items, a jump moves the mission itself."""
from __future__ import annotations

import pytest
from gcs_support import HOME, FakeStack, Log, from_gcs, item_int, square, upload
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import (
    GetMissionReply, LoadMissionReply, Mission, MissionStatus, Reply, Waypoint, parse_mission,
)
from aeroperception.schemas.system import ParamDescriptor
from aeroperception.services.gcs.mission_progress import Progress
from aeroperception.services.gcs.mission_sync import MissionSync
from aeroperception.services.gcs.ops import StackOps
from aeroperception.services.gcs.params import ParamTable
from aeroperception.services.gcs.telemetry import TelemetryState
from aeroperception.services.runtime import CallError


class Rig:
    def __init__(self):
        self.stack, self.sent, self.notes = FakeStack(), [], []
        table = ParamTable(["planner", "mission"], aliases=())
        table.update_service("planner", [ParamDescriptor(name="max_velocity_mps", value=2.0, min=0.5, max=10.0),
                                         ParamDescriptor(name="acceptance_radius_m", value=0.8)])
        table.update_service("mission", [ParamDescriptor(name="takeoff_altitude_m", value=4.0)])
        self.tel = TelemetryState(HOME)
        progress = self.tel.progress = Progress()
        self.ops = StackOps(self.stack, 1.0, table, self.tel, progress, Log())
        self.sync = MissionSync(self.ops, progress, self.tel, table, lambda: HOME,
                                lambda m, broadcast=False: self.sent.append(m),
                                lambda text, peer, severity=M.MAV_SEVERITY_CRITICAL: self.notes.append(text), Log(),
                                item_timeout_s=0.25, retries=3, max_items=100)

    def handle(self, msg) -> None:
        self.sync.protocol.handle(msg, 0.0)


def test_an_upload_is_converted_about_home_and_loaded_and_acked_once_the_mission_took_it():
    rig = Rig()
    upload(rig.sync.protocol, rig.sent, square(2))
    ((key, request),) = rig.stack.calls
    mission = parse_mission(request.mission_json)
    assert key == "mission/srv/load" and mission.mission_id == "gcs-1"
    assert mission.takeoff_altitude_m == 4.0 and mission.waypoint_acceptance_radius_m == 0.8   # the services' defaults
    assert (mission.waypoints[1].x, mission.waypoints[1].y) == pytest.approx((0.0, 10.0), abs=0.02)
    assert rig.sent[-1].get_type() == "MISSION_REQUEST_INT"                  # no ACK before the mission answers
    rig.stack.answer(LoadMissionReply(success=True, message="loaded", mission_id="gcs-1", num_waypoints=2))
    assert rig.sent[-1].get_type() == "MISSION_ACK" and rig.sent[-1].type == M.MAV_MISSION_ACCEPTED
    assert (rig.tel.mission_total, rig.tel.mission_id) == (2, rig.sync.protocol.plan_id)
    assert rig.sync.synced == ("gcs-1", 2) and rig.ops.speeds.mission_id == "gcs-1"

    upload(rig.sync.protocol, rig.sent, square(3))
    rig.stack.answer(CallError("timeout calling mission/srv/load"))          # no answer: an error, not a refusal
    assert rig.sent[-1].type == M.MAV_MISSION_ERROR and len(rig.sync.protocol.items) == 2
    assert rig.notes[-1] == "Mission rejected: timeout calling mission/srv/load"


def test_a_speed_outside_the_planners_range_is_refused_before_loading():
    rig = Rig()
    (lat, lon, alt), _ = square(2)
    rig.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)))
    rig.handle(item_int(0, lat, lon, alt, cmd=M.MAV_CMD_DO_CHANGE_SPEED, frame=M.MAV_FRAME_MISSION, p1=1.0, p2=25.0))
    rig.handle(item_int(1, lat, lon, alt))
    assert rig.stack.calls == [] and rig.sent[-1].type == M.MAV_MISSION_INVALID_PARAM2
    assert rig.notes[-1].startswith("Mission rejected: DO_CHANGE_SPEED 25.0 m/s outside PLN_MAX_VELOCITY [0.5, 10.0]")


def test_a_mission_loaded_elsewhere_is_fetched_and_served_as_items():
    rig = Rig()
    mission = Mission(mission_id="aero-square", takeoff_altitude_m=5.0,
                      waypoints=[Waypoint(x=0.0, y=10.0, z=5.0), Waypoint(x=10.0, y=10.0, z=5.0)])
    rig.sync.on_status(MissionStatus(mission_id="aero-square", total_waypoints=2))
    assert rig.stack.asked() == [("mission/srv/get", None)]
    rig.sync.on_status(MissionStatus(mission_id="aero-square", total_waypoints=2))
    assert len(rig.stack.calls) == 1                                          # one fetch at a time
    rig.stack.answer(GetMissionReply(success=True, mission_id="aero-square", num_waypoints=2,
                                     mission_json=mission.to_json()))
    items = rig.sync.protocol.items
    assert [it.command for it in items] == [M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_WAYPOINT]
    assert rig.sync.synced == ("aero-square", 2) and rig.sync.progress.wp_seqs == [1, 2]
    rig.sync.on_status(MissionStatus(mission_id="aero-square", total_waypoints=2))
    assert len(rig.stack.calls) == 1                                          # in sync: nothing to fetch

    assert rig.sync.set_current(2) and rig.stack.asked()[-1] == ("mission/srv/command", "SET_CURRENT")
    assert rig.stack.calls[-1][1].waypoint_index == 1 and rig.tel.mission_seq == 2
    rig.stack.answer(Reply(success=False, message="no mission running"))
    assert rig.notes[-1] == "Mission jump to item 2 refused: no mission running"
    assert not rig.sync.set_current(7) and len(rig.stack.calls) == 2          # past the last item: no jump
