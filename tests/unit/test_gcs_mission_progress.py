"""Mission progress as MAVLink reports it: every item reached once per run, MISSION_CURRENT's
state, COMPLETE with seq == total."""
from __future__ import annotations

from gcs_support import HOME, speed_item, takeoff_item, wp_item
from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.mission_items import Item
from aeroperception.services.gcs.mission_progress import Progress, takeoff_seq
from aeroperception.services.gcs.telemetry import TelemetryState


def test_takeoff_item_reached_once_per_run_before_the_first_waypoint():
    items = [takeoff_item(0), speed_item(1, 2.0), wp_item(2, 4, 0), wp_item(3, 4, 4)]
    assert takeoff_seq(items) == 0
    assert takeoff_seq([speed_item(0, 2.0), takeoff_item(1), wp_item(2, 4, 0)]) == 1
    assert takeoff_seq([wp_item(0, 4, 0), takeoff_item(1)]) is None and takeoff_seq([]) is None
    pr = Progress()
    pr.load("gcs-1", items, [2, 3])
    assert pr.on_status("gcs-1", "IDLE", 0, 2) == [] and pr.state == M.MISSION_STATE_NOT_STARTED
    assert pr.on_status("gcs-1", "TAKEOFF", 0, 2) == [] and pr.state == M.MISSION_STATE_ACTIVE
    assert pr.on_status("gcs-1", "HOLDING", 0, 2) == [] and pr.state == M.MISSION_STATE_PAUSED
    assert pr.on_status("gcs-1", "EXECUTING", 0, 2) == [0, 1]   # takeoff done (+ the DO item after it)
    assert pr.on_status("gcs-1", "EXECUTING", 0, 2) == [] and pr.current == 2
    assert pr.on_reached("gcs-1", 0) == [2] and pr.current == 3
    assert pr.on_reached("gcs-1", 2) == [] and pr.on_reached("aero-square", 0) == []   # not ours
    assert pr.on_reached("gcs-1", 1) == [3]                      # the last one: complete
    assert (pr.state, pr.current, pr.total) == (M.MISSION_STATE_COMPLETE, 4, 4)
    assert pr.on_status("gcs-1", "EXECUTING", 1, 2) == []        # a status that lagged behind: still complete
    assert pr.on_status("gcs-1", "LAND", 2, 2) == [] and pr.state == M.MISSION_STATE_COMPLETE
    assert pr.on_status("gcs-1", "IDLE", 2, 2) == [] and pr.state == M.MISSION_STATE_COMPLETE
    assert pr.on_reached("gcs-1", 0) == [0, 1, 2]                # next run: a waypoint before the status
    assert pr.on_status("aero-square", "EXECUTING", 0, 5) == []
    pr.load("gcs-2", [wp_item(0, 4, 0), wp_item(1, 4, 4)], [0, 1])   # no takeoff item: nothing for it
    assert pr.on_status("gcs-2", "TAKEOFF", 0, 2) == [] and pr.on_status("gcs-2", "EXECUTING", 0, 2) == []
    assert pr.on_reached("gcs-2", 0) == [0]


def test_mission_progress_every_item_reached_and_complete_per_mavlink():
    """A trailing NAV_LAND without a position is reached once landed, then COMPLETE
    with seq == total; an aborted run is PAUSED; RTL items are never reported reached (PX4)."""
    land = Item(seq=4, frame=M.MAV_FRAME_MISSION, command=M.MAV_CMD_NAV_LAND)
    items = [takeoff_item(0), wp_item(1, 4, 0), wp_item(2, 4, 4), speed_item(3, 2.0), land]
    pr = Progress()
    pr.load("gcs-1", items, [1, 2])
    assert (pr.state, pr.mode) == (M.MISSION_STATE_NOT_STARTED, 0)
    pr.on_status("gcs-1", "IDLE", 0, 2)
    pr.on_status("gcs-1", "TAKEOFF", 0, 2)
    assert pr.on_status("gcs-1", "EXECUTING", 0, 2) == [0] and (pr.current, pr.mode) == (1, 1)
    assert pr.on_reached("gcs-1", 0) == [1]
    assert pr.on_reached("gcs-1", 1) == [2, 3]                   # + the DO item right after it
    assert (pr.state, pr.current) == (M.MISSION_STATE_ACTIVE, 4)   # landing: the LAND item is current
    assert pr.on_status("gcs-1", "LAND", 2, 2) == [] and pr.state == M.MISSION_STATE_ACTIVE
    assert pr.on_status("gcs-1", "IDLE", 2, 2) == [4]            # landed: the last item reached
    assert (pr.state, pr.current, pr.total) == (M.MISSION_STATE_COMPLETE, 5, 5)

    # the same mission stopped by an RTL command halfway: PAUSED at its item, nothing reached after
    pr.on_status("gcs-1", "TAKEOFF", 0, 2)
    assert pr.state == M.MISSION_STATE_ACTIVE and pr.upto == -1   # a new run
    pr.on_status("gcs-1", "EXECUTING", 0, 2)
    assert pr.on_status("gcs-1", "LAND", 0, 2) == [] and (pr.state, pr.current, pr.mode) == (M.MISSION_STATE_PAUSED, 1, 2)
    assert pr.on_status("gcs-1", "IDLE", 0, 2) == [] and pr.state == M.MISSION_STATE_PAUSED

    rtl = Item(seq=2, frame=M.MAV_FRAME_MISSION, command=M.MAV_CMD_NAV_RETURN_TO_LAUNCH)
    pr.load("gcs-3", [wp_item(0, 4, 0), wp_item(1, 4, 4), rtl], [0, 1, 2])   # RTL flies back above home
    pr.on_status("gcs-3", "TAKEOFF", 0, 3)
    assert pr.on_reached("gcs-3", 0) == [0] and pr.on_reached("gcs-3", 1) == [1]
    assert pr.on_reached("gcs-3", 2) == [] and (pr.state, pr.current) == (M.MISSION_STATE_COMPLETE, 3)

    tel = TelemetryState(HOME, mission_total=3, mission_id=7, progress=pr)
    mc = tel.mission_current()
    assert (mc.seq, mc.total, mc.mission_state, mc.mission_id) == (3, 3, M.MISSION_STATE_COMPLETE, 7)
