"""DO_CHANGE_SPEED items: the speed per waypoint, applied once per start, and scoped to the
mission (restored when it is over)."""
from __future__ import annotations

import math

import pytest
from gcs_support import HOME, speed_item, wp_item
from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.mission_items import Item, MissionConversionError, convert_items
from aeroperception.services.gcs.mission_speed import SPEED_DEFAULT, SpeedSchedule, waypoint_speeds


def test_do_change_speed_items_give_the_speed_per_waypoint():
    items = [Item(seq=0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                  x=HOME.lat_deg, y=HOME.lon_deg, z=4.0, param4=math.nan),
             speed_item(1, 1.5, kind=0.0),          # airspeed: same as ground speed here
             speed_item(2, 3.0),                    # the last one before the first waypoint wins
             wp_item(3, 4, 0),
             wp_item(4, 4, 4),
             speed_item(5, -1.0),                   # no change
             speed_item(6, 0.7, kind=2.0),          # climb speed: ignored
             wp_item(7, 0, 4),
             speed_item(8, -2.0),                   # back to the default
             wp_item(9, 0, 0)]
    mission, seqs = convert_items(items, HOME)
    assert seqs == [3, 4, 7, 9] and len(mission.waypoints) == 4
    assert waypoint_speeds(items, seqs) == [3.0, 3.0, 3.0, SPEED_DEFAULT]
    assert waypoint_speeds([wp_item(0, 1, 1), speed_item(1, 2.0), wp_item(2, 2, 2)], [0, 2]) == [None, 2.0]
    # invalid speeds / types refuse the upload, naming the item and the parameter
    for bad, result in ((speed_item(1, 0.0), M.MAV_MISSION_INVALID_PARAM2),
                        (speed_item(1, -5.0), M.MAV_MISSION_INVALID_PARAM2),
                        (speed_item(1, 2.0, kind=7.0), M.MAV_MISSION_INVALID_PARAM1)):
        with pytest.raises(MissionConversionError) as e:
            convert_items([wp_item(0, 1, 1), bad, wp_item(2, 2, 2)], HOME)
        assert e.value.result == result and "item 1" in str(e.value)


def test_speed_schedule_applies_each_speed_once_per_start():
    sched = SpeedSchedule([None, 3.0, 3.0, SPEED_DEFAULT], "gcs-1")
    assert sched.due(0) is None                       # no DO_CHANGE_SPEED before waypoint 0
    assert sched.due(1) == 3.0 and sched.due(1) is None and sched.due(2) is None
    assert sched.due(3) == SPEED_DEFAULT and sched.due(4) is None and sched.due(-1) is None
    sched.reset()                                     # the mission starts again
    assert sched.due(2) == 3.0
    assert SpeedSchedule().due(0) is None


def test_mission_speed_ends_with_the_mission():
    """A speed set for a mission is restored when the mission completes, lands, is
    replaced or fails to start; not while it is only paused, not before it was seen running."""
    s = SpeedSchedule([5.0, 5.0], "gcs-1")
    assert s.due(0) == 5.0
    s.begin(2.0)
    s.begin(5.0)                                          # later changes keep the speed from before
    assert s.observe("gcs-1", "IDLE", 0, 2) is None      # the start is still on its way (status lags)
    assert s.observe("gcs-1", "TAKEOFF", 0, 2) is None
    assert s.observe("gcs-1", "EXECUTING", 1, 2) is None
    assert s.observe("gcs-1", "HOLDING", 1, 2) is None   # paused: still the mission's speed
    assert s.observe("gcs-1", "LAND", 2, 2) == 2.0       # last waypoint reached: restored, once
    assert s.observe("gcs-1", "IDLE", 2, 2) is None and s.restore is None
    for over in (("gcs-1", "LAND", 1, 2), ("gcs-1", "IDLE", 1, 2), ("gcs-1", "HOLDING", 2, 2)):
        s.begin(2.0)
        s.observe("gcs-1", "EXECUTING", 0, 2)
        assert s.observe(*over) == 2.0, over             # RTL/LAND mid-mission, landed, complete+hold
    s.begin(2.0)
    assert s.observe("other", "IDLE", -1, 3) == 2.0      # replaced, even before it ran
    s.begin(2.0)
    assert s.end() == 2.0 and s.end() is None            # a failed start: the caller restores
