"""MAVLink mission items <-> the stack's Mission: frames, takeoff/land/RTL/yaw, refusals naming
the item (unsupported, at or below home), and back to items for a download."""
from __future__ import annotations

import math

import pytest
from gcs_support import HOME, proto, square, takeoff_item, upload, wp_item
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import Mission, Waypoint
from aeroperception.services.gcs.mission_items import (
    Item, MissionConversionError, convert_items, items_to_mission, mission_to_items,
)


def test_items_to_mission_takeoff_waypoints_land_and_yaw():
    pts = square()
    items = [Item(seq=0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                  x=HOME.lat_deg, y=HOME.lon_deg, z=4.0, param4=math.nan)]
    for i, (lat, lon, alt) in enumerate(pts):
        items.append(Item(seq=i + 1, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                          x=lat, y=lon, z=alt, param4=90.0 if i == 1 else math.nan))
    items.append(Item(seq=5, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_DO_CHANGE_SPEED, param2=3.0))
    items.append(Item(seq=6, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_LAND))
    mission, seqs = convert_items(items, HOME)
    assert mission.takeoff_altitude_m == pytest.approx(4.0, abs=1e-3)
    assert len(mission.waypoints) == 4 and seqs == [1, 2, 3, 4]
    w = mission.waypoints[1]
    assert (w.x, w.y, w.z) == pytest.approx((0.0, 10.0, 5.0), abs=1e-3)   # 10 m north = ENU y
    assert w.yaw_deg == pytest.approx(0.0, abs=1e-6)                     # NED heading 90 (East) = ENU yaw 0
    assert mission.waypoints[2].x == pytest.approx(10.0, abs=1e-3)


def test_local_and_absolute_frames():
    ned = Item(seq=0, frame=M.MAV_FRAME_LOCAL_NED, command=M.MAV_CMD_NAV_WAYPOINT, x=3.0, y=4.0, z=-6.0)
    amsl = Item(seq=1, frame=M.MAV_FRAME_GLOBAL_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                x=HOME.lat_deg, y=HOME.lon_deg, z=HOME.alt_m + 2.5)
    m = items_to_mission([ned, amsl], HOME)
    assert (m.waypoints[0].x, m.waypoints[0].y, m.waypoints[0].z) == pytest.approx((4.0, 3.0, 6.0))
    assert m.waypoints[1].z == pytest.approx(2.5, abs=1e-6)


def test_unsupported_items_are_refused_with_a_reason():
    with pytest.raises(MissionConversionError) as e:
        items_to_mission([Item(seq=0, frame=3, command=M.MAV_CMD_NAV_LOITER_UNLIM)], HOME)
    assert e.value.result == M.MAV_MISSION_UNSUPPORTED
    with pytest.raises(MissionConversionError) as e:
        items_to_mission([Item(seq=0, frame=M.MAV_FRAME_BODY_FRD, command=M.MAV_CMD_NAV_WAYPOINT)], HOME)
    assert e.value.result == M.MAV_MISSION_UNSUPPORTED_FRAME


def test_mission_to_items_round_trip():
    mission = Mission(takeoff_altitude_m=4.0, waypoints=[Waypoint(x=5.0, y=-3.0, z=6.0, yaw_deg=45.0)])
    items = mission_to_items(mission, HOME)
    assert [it.command for it in items] == [M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_WAYPOINT]
    back = items_to_mission(items, HOME)
    w = back.waypoints[0]
    assert (w.x, w.y, w.z, w.yaw_deg) == pytest.approx((5.0, -3.0, 6.0, 45.0), abs=1e-3)
    assert back.takeoff_altitude_m == pytest.approx(4.0)


class ConvertingLoader:
    """Like gcs's _load: an item the conversion refuses refuses the upload with its result."""

    def __call__(self, items, done):
        try:
            convert_items(items, HOME)
        except MissionConversionError as e:
            done(False, str(e), e.result)
            return
        done(True, "ok", M.MAV_MISSION_ACCEPTED)


def test_waypoint_at_or_below_home_is_refused_naming_the_item():
    for z in (0.0, -3.0):
        with pytest.raises(MissionConversionError) as e:
            convert_items([takeoff_item(0), wp_item(1, 5, 5), wp_item(2, 5, 0, alt=z)], HOME)
        assert e.value.result == M.MAV_MISSION_INVALID_PARAM7 and "item 2" in str(e.value)
    lat, lon = HOME.projection.reproject(5, 5)
    rel = M.MAV_FRAME_GLOBAL_RELATIVE_ALT
    # NAV_LAND and RTL at 0 m are fine
    convert_items([wp_item(0, 5, 5), Item(seq=1, frame=rel, command=M.MAV_CMD_NAV_LAND, x=lat, y=lon, z=0.0)], HOME)
    convert_items([wp_item(0, 5, 5), Item(seq=1, frame=rel, command=M.MAV_CMD_NAV_RETURN_TO_LAUNCH, z=0.0)], HOME)
    # an AMSL item at (or below) home altitude is refused like a relative one, naming it;
    # so is a local item at or below home; above home both are fine
    for frame, z in ((M.MAV_FRAME_GLOBAL_INT, HOME.alt_m), (M.MAV_FRAME_GLOBAL, HOME.alt_m - 1.0),
                     (M.MAV_FRAME_LOCAL_NED, 0.0), (M.MAV_FRAME_LOCAL_ENU, -2.0)):
        x, y = (lat, lon) if frame in (M.MAV_FRAME_GLOBAL_INT, M.MAV_FRAME_GLOBAL) else (5.0, 5.0)
        with pytest.raises(MissionConversionError) as e:
            items_to_mission([wp_item(0, 5, 5), Item(seq=1, frame=frame, command=M.MAV_CMD_NAV_WAYPOINT,
                                                     x=x, y=y, z=z)], HOME)
        assert e.value.result == M.MAV_MISSION_INVALID_PARAM7 and str(e.value).startswith("item 1: "), frame
    assert "m AMSL, home 10.0 m" in str(pytest.raises(MissionConversionError, items_to_mission, [Item(
        seq=0, frame=M.MAV_FRAME_GLOBAL_INT, command=M.MAV_CMD_NAV_WAYPOINT, x=lat, y=lon, z=HOME.alt_m)], HOME).value)
    m = items_to_mission([Item(seq=0, frame=M.MAV_FRAME_GLOBAL_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                               x=lat, y=lon, z=HOME.alt_m + 4.0)], HOME)
    assert m.waypoints[0].z == pytest.approx(4.0)

    # over the protocol: a STATUSTEXT naming the item, then the error ACK; nothing loaded
    p, sent = proto(ConvertingLoader())
    (lat0, lon0, _), (lat1, lon1, _) = square(2)
    ack = upload(p, sent, [(lat0, lon0, 5.0), (lat1, lon1, 0.0)])
    assert ack.get_type() == "MISSION_ACK" and ack.type == M.MAV_MISSION_INVALID_PARAM7
    texts = [m for m in sent if m.get_type() == "STATUSTEXT"]
    assert texts and all(t.severity == M.MAV_SEVERITY_CRITICAL for t in texts)
    text = "".join(t.text for t in texts)
    assert text.startswith("Mission rejected: item 1") and "below home" in text
    assert sent.index(texts[-1]) < sent.index(ack) and p.items == [] and p.uploads_rejected == 1
