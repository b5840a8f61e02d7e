"""gcs logic without Zenoh: mission protocol with pymavlink message objects, item conversion,
parameter names and values, commands, telemetry encoding, garbage on the link."""
from __future__ import annotations

import math
import os
import socket
import struct
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")   # mavutil picks the MAVLink 2 dialect (signing needs it)
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aeroperception.schemas import HomePosition, Mission, Quaternion, Vector3, VehicleState, Waypoint
from aeroperception.services.gcs.commands import CommandHandler, mode_from_set_mode
from aeroperception.services.gcs.home import HomeTracker, home_from_msg, origin_shift_m
from aeroperception.services.gcs.link import (
    Parser, UdpLink, load_signing_key, make_mav, parse_signing_key, signing_timestamp,
)
from aeroperception.services.gcs.messages import extension_fields, statustext
from aeroperception.services.gcs.missions import (
    SPEED_DEFAULT, Home, Item, MissionConversionError, MissionProtocol, Progress, SpeedSchedule, convert_items,
    items_to_mission, mission_to_items, plan_id, takeoff_seq, waypoint_speeds,
)
from aeroperception.services.gcs.params import (
    ParamTable, decode_value, encode_value, mavlink_name,
)
from aeroperception.services.gcs.telemetry import CAPABILITIES, Scheduler, TelemetryState
from aeroperception.services.mavlink import ftp, px4
from aeroperception.services.mavlink.geo import MapProjection
from aeroperception.schemas.system import ParamDescriptor

HOME = Home(35.736805, 139.539676, 10.0)
GCS = make_mav(255, 190)


def from_gcs(msg):
    """A message as the ground station would send it (packed and parsed, so src ids are set)."""
    data = msg.pack(GCS)
    out = Parser().feed(data)
    assert len(out) == 1
    return out[0]


def item_int(seq, lat, lon, alt, cmd=M.MAV_CMD_NAV_WAYPOINT, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, **kw):
    return from_gcs(M.MAVLink_mission_item_int_message(
        1, 1, seq, frame, cmd, 0, 1, kw.get("p1", 0.0), kw.get("p2", 0.0), 0.0, kw.get("p4", math.nan),
        int(round(lat * 1e7)), int(round(lon * 1e7)), alt, 0))


class Loader:
    def __init__(self, accept=True, sync=True):
        self.accept, self.sync, self.calls, self.pending = accept, sync, [], None

    def __call__(self, items, done):
        self.calls.append(items)
        if self.sync:
            mission, _ = convert_items(items, HOME) if self.accept else (None, None)
            done(self.accept, "ok" if self.accept else "rejected", M.MAV_MISSION_DENIED)
        else:
            self.pending = done


def proto(loader=None, **kw):
    sent = []
    p = MissionProtocol(sent.append, loader or Loader(), **kw)
    return p, sent


def square(n=4, alt=5.0):
    out = []
    for i in range(n):
        north, east = (0, 10, 10, 0)[i % 4], (0, 0, 10, 10)[i % 4]
        lat, lon = HOME.projection.reproject(north, east)
        out.append((lat, lon, alt))
    return out


def upload(p, sent, points, now=0.0):
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, len(points), 0)), now)
    for i, (lat, lon, alt) in enumerate(points):
        req = sent[-1]
        assert req.get_type() == "MISSION_REQUEST_INT" and req.seq == i
        p.handle(item_int(i, lat, lon, alt), now)
    return sent[-1]


# ---------------------------------------------------------------- conversion


def test_global_relative_to_enu_about_home_and_back():
    lat, lon = HOME.projection.reproject(20.0, -5.0)   # 20 m north, 5 m west
    x, y, z = HOME.to_enu(lat, lon, 7.0)
    assert (x, y, z) == pytest.approx((-5.0, 20.0, 7.0), abs=1e-3)
    back = HOME.to_geodetic(x, y, z)
    assert back == pytest.approx((lat, lon, 7.0), abs=1e-9)


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


def speed_item(seq, speed, kind=1.0):
    return Item(seq=seq, frame=M.MAV_FRAME_MISSION, command=M.MAV_CMD_DO_CHANGE_SPEED, param1=kind, param2=speed,
                param3=-1.0)


def wp_item(seq, north, east, alt=5.0):
    lat, lon = HOME.projection.reproject(north, east)
    return Item(seq=seq, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                x=lat, y=lon, z=alt, param4=math.nan)


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


def test_mission_to_items_round_trip():
    mission = Mission(takeoff_altitude_m=4.0, waypoints=[Waypoint(x=5.0, y=-3.0, z=6.0, yaw_deg=45.0)])
    items = mission_to_items(mission, HOME)
    assert [it.command for it in items] == [M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_WAYPOINT]
    back = items_to_mission(items, HOME)
    w = back.waypoints[0]
    assert (w.x, w.y, w.z, w.yaw_deg) == pytest.approx((5.0, -3.0, 6.0, 45.0), abs=1e-3)
    assert back.takeoff_altitude_m == pytest.approx(4.0)


# ---------------------------------------------------------------- the flight controller's home

ZURICH = (47.397742, 8.545594, 488.0)     # the sim's (PX4 SITL's) default home


def fc_home(local=(0.0, 0.0, 0.0), lat=ZURICH[0], lon=ZURICH[1], alt=ZURICH[2]) -> Home:
    return home_from_msg(HomePosition(latitude_deg=lat, longitude_deg=lon, altitude_amsl_m=alt,
                                      position_m=Vector3(x=local[0], y=local[1], z=local[2])))


def test_home_with_a_local_offset_projects_about_the_local_origin_like_px4():
    # PX4: global = MapProjection(EKF origin).reproject(local NED); home is some local point.
    origin = MapProjection(47.39, 8.54)
    local_home = (30.0, -12.0, 0.4)                       # ENU: 30 m East, 12 m South, 0.4 m up
    lat, lon = origin.reproject(north_m=local_home[1], east_m=local_home[0])
    home = fc_home(local_home, lat, lon, 500.0)
    assert (home.origin.lat_deg, home.origin.lon_deg) == pytest.approx((47.39, 8.54), abs=1e-11)
    for x, y in ((0.0, 0.0), (30.0, -12.0), (250.0, 400.0), (-900.0, 1200.0)):
        want = origin.reproject(north_m=y, east_m=x)
        got = home.to_geodetic(x, y, 3.0)
        assert got[:2] == pytest.approx(want, abs=1e-10)
        assert got[2] == pytest.approx(2.6)                  # above home, not above the local origin
        assert home.to_enu(*got) == pytest.approx((x, y, 3.0), abs=1e-4)
    assert home.to_geodetic(*local_home) == pytest.approx((lat, lon, 0.0), abs=1e-10)   # home is home
    assert home.local_z(5.0) == pytest.approx(5.4)


def test_home_from_msg_refuses_non_finite_or_out_of_range():
    assert fc_home() == Home(*ZURICH)
    assert home_from_msg(HomePosition(latitude_deg=math.nan, longitude_deg=8.0)) is None
    assert home_from_msg(HomePosition(latitude_deg=47.0, longitude_deg=200.0)) is None
    assert home_from_msg(HomePosition(latitude_deg=47.0, longitude_deg=8.0, position_m=Vector3(x=math.inf))) is None


def test_telemetry_about_the_flight_controllers_home():
    home = fc_home((2.0, 1.0, -0.5))
    st = VehicleState(position_m=Vector3(x=2.0, y=1.0, z=-0.5), connected=True)   # the vehicle is at home
    tel = TelemetryState(home, vehicle=st)
    gp = tel.global_position_int()
    assert (gp.lat / 1e7, gp.lon / 1e7) == pytest.approx(ZURICH[:2], abs=1e-7)
    assert gp.relative_alt == 0 and gp.alt == 488000
    raw = tel.gps_raw_int()   # the FC's GPS receiver (test_gcs_gps), never this projection dressed as a fix
    assert (raw.fix_type, raw.lat, raw.lon) == (M.GPS_FIX_TYPE_NO_GPS, 0, 0)
    hp = tel.home_position()
    assert (hp.latitude, hp.longitude, hp.altitude) == (473977420, 85455940, 488000)
    assert (hp.x, hp.y, hp.z) == pytest.approx((1.0, 2.0, 0.5))       # home in local NED


def test_mission_items_and_commands_about_the_flight_controllers_home():
    home = fc_home((2.0, 1.0, -0.5))
    lat, lon, _ = home.to_geodetic(12.0, 1.0, 0.0)                  # 10 m East of home
    items = [Item(seq=0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                  x=home.lat_deg, y=home.lon_deg, z=4.0, param4=math.nan),
             Item(seq=1, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                  x=lat, y=lon, z=5.0, param4=math.nan),
             Item(seq=2, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_RETURN_TO_LAUNCH)]
    mission, _ = convert_items(items, home)
    assert mission.takeoff_altitude_m == pytest.approx(3.5)         # 4 m above home, home at z = -0.5
    w, rtl = mission.waypoints
    assert (w.x, w.y, w.z) == pytest.approx((12.0, 1.0, 4.5), abs=1e-3)
    assert (rtl.x, rtl.y) == (2.0, 1.0)
    back = mission_to_items(mission, home)
    assert back[0].z == pytest.approx(4.0) and (back[1].x, back[1].y, back[1].z) == pytest.approx((lat, lon, 5.0))

    sent, ops = [], FakeOps()
    h = CommandHandler(sent.append, ops, home, position_enu=lambda: (1.0, 2.0, 3.0),
                       request_message=lambda mid, p2: M.MAV_RESULT_ACCEPTED, set_interval=lambda mid, us: True,
                       set_current=lambda s: True)
    h.handle(cmd_long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, home.alt_m + 5.0), 0.0)
    assert ops.calls[-1] == ("takeoff", pytest.approx(4.5))
    h.handle(from_gcs(M.MAVLink_command_int_message(1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_REPOSITION,
                                                    0, 0, -1, 0, 0, math.nan, int(round(lat * 1e7)),
                                                    int(round(lon * 1e7)), 6.0)), 0.0)
    assert ops.calls[-1][:2] == ("goto", pytest.approx((12.0, 1.0, 5.5), abs=0.02))


def test_home_tracker_uses_the_fallback_until_the_flight_controller_reports_one():
    applied = []
    fallback = HOME
    t = HomeTracker(fallback, busy=lambda: False, apply=lambda new, old, src: applied.append((new, old, src)))
    assert t.home == fallback and t.source == "param"
    zurich = fc_home()
    assert t.offer(zurich) and t.home == zurich and t.source == "flight_controller"
    assert applied == [(zurich, fallback, "flight_controller")]
    assert not t.offer(fc_home())                              # the 1 Hz repeat: nothing happens
    moved = fc_home((3.0, 4.0, 0.0), *MapProjection(*ZURICH[:2]).reproject(4.0, 3.0), 488.0)
    assert t.offer(moved) and len(applied) == 2                  # PX4 moved home (e.g. armed elsewhere)
    assert origin_shift_m(zurich, moved) == pytest.approx(0.0, abs=1e-3)   # ... same local frame
    assert origin_shift_m(fallback, zurich) > 8e6               # Tokyo -> Zurich


def test_home_change_waits_for_the_mission_upload_under_way():
    """An upload is converted about the home in force when it started; the FC's new home is held
    back until the upload is loaded, then applied."""
    loaded = []
    tracker = None

    def loader(items, done):                                 # like gcs's _load: converts about the home in force
        loaded.append(convert_items(items, tracker.home)[0])
        done(True, "ok", M.MAV_MISSION_ACCEPTED)

    p, sent = proto(loader)
    tracker = HomeTracker(HOME, busy=lambda: p.loading or (p.transfer is not None and p.transfer.direction == "upload"))
    pts = square(2)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)), 0.0)
    p.handle(item_int(0, *pts[0]), 0.0)
    assert not tracker.offer(fc_home())                      # mid-upload: held back
    assert tracker.home == HOME and tracker.pending == fc_home() and not tracker.poll()
    p.handle(item_int(1, *pts[1]), 0.0)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_ACCEPTED
    w = loaded[0].waypoints[1]
    assert (w.x, w.y) == pytest.approx((0.0, 10.0), abs=0.02)   # about the home the upload started with
    assert tracker.poll() and tracker.home == fc_home() and tracker.pending is None
    assert not tracker.poll()


def test_home_change_waits_for_an_asynchronous_load():
    loader = Loader(sync=False)
    p, sent = proto(loader)
    t = HomeTracker(HOME, busy=lambda: p.loading or (p.transfer is not None and p.transfer.direction == "upload"))
    upload(p, sent, square(1))
    assert p.loading and not t.offer(fc_home()) and t.home == HOME
    loader.pending(True, "ok", 0)
    assert t.poll() and t.home == fc_home()


# ---------------------------------------------------------------- protocol


def test_upload_requests_each_item_then_acks_and_download_returns_it():
    loader = Loader()
    p, sent = proto(loader)
    ack = upload(p, sent, square())
    assert ack.get_type() == "MISSION_ACK" and ack.type == M.MAV_MISSION_ACCEPTED
    assert len(loader.calls) == 1 and len(p.items) == 4
    sent.clear()
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, 0)), 1.0)
    assert sent[-1].get_type() == "MISSION_COUNT" and sent[-1].count == 4
    for i in range(4):
        p.handle(from_gcs(M.MAVLink_mission_request_int_message(1, 1, i, 0)), 1.0)
        it = sent[-1]
        assert it.get_type() == "MISSION_ITEM_INT" and it.seq == i
        assert it.x == int(round(square()[i][0] * 1e7)) and it.z == pytest.approx(5.0)
    p.handle(from_gcs(M.MAVLink_mission_ack_message(1, 1, 0, 0)), 1.0)
    assert p.transfer is None


def test_rejected_upload_keeps_previous_mission():
    p, sent = proto(Loader(accept=True))
    upload(p, sent, square())
    p.load = Loader(accept=False)
    ack = upload(p, sent, square(2))
    assert ack.type == M.MAV_MISSION_DENIED
    assert len(p.items) == 4


def test_ack_waits_for_asynchronous_load():
    loader = Loader(sync=False)
    p, sent = proto(loader)
    upload(p, sent, square(1))
    assert sent[-1].get_type() == "MISSION_ITEM_INT" or sent[-1].get_type() == "MISSION_REQUEST_INT"
    assert loader.pending is not None and p.loading
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)   # busy meanwhile
    assert sent[-1].type == M.MAV_MISSION_DENIED
    loader.pending(True, "ok", 0)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_ACCEPTED


def test_rerequest_on_timeout_then_give_up():
    p, sent = proto(item_timeout_s=0.1, retries=2)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)), 0.0)
    assert len(sent) == 1
    p.tick(0.05)
    assert len(sent) == 1
    p.tick(0.15)
    assert len(sent) == 2 and sent[-1].seq == 0
    p.tick(0.30)
    p.tick(0.45)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_OPERATION_CANCELLED
    assert p.transfer is None and p.errors["upload_timeout"] == 1


def test_out_of_order_items_and_absurd_count_are_counted_not_fatal():
    p, sent = proto(max_items=100)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 60000, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_NO_SPACE
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 3, 0)), 0.0)
    lat, lon, alt = square()[0]
    p.handle(item_int(2, lat, lon, alt), 0.0)            # ahead: re-request seq 0
    assert sent[-1].get_type() == "MISSION_REQUEST_INT" and sent[-1].seq == 0
    p.handle(item_int(0, lat, lon, alt), 0.0)
    p.handle(item_int(0, lat, lon, alt), 0.0)            # duplicate: ignored
    assert sent[-1].seq == 1
    p.handle(item_int(7, lat, lon, alt), 0.0)
    assert p.errors["item_out_of_order"] == 3
    p.handle(from_gcs(M.MAVLink_mission_request_int_message(1, 1, 99, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_INVALID_SEQUENCE


def test_legacy_mission_item_and_request_accepted():
    p, sent = proto()
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)
    lat, lon, alt = square()[1]
    p.handle(from_gcs(M.MAVLink_mission_item_message(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                                     M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, lat, lon, alt, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_ACCEPTED
    p.handle(from_gcs(M.MAVLink_mission_request_message(1, 1, 0, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_ITEM" and sent[-1].x == pytest.approx(lat)


def test_clear_all_and_fence_rally_are_empty():
    p, sent = proto()
    upload(p, sent, square())
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, M.MAV_MISSION_TYPE_FENCE)), 0.0)
    assert sent[-1].count == 0 and sent[-1].mission_type == M.MAV_MISSION_TYPE_FENCE
    p.handle(from_gcs(M.MAVLink_mission_clear_all_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_ACCEPTED and p.items == []


# ---------------------------------------------------------------- parameters


def test_param_names_fit_16_chars_are_stable_and_unique():
    assert mavlink_name("planner", "max_velocity_mps") == "PLN_MAX_VELOCITY"
    assert mavlink_name("planner", "kp") == "PLN_KP"
    assert mavlink_name("mission", "takeoff_altitude_m").startswith("MIS_TAKEO")
    t = ParamTable(["planner", "mission"], aliases=())
    t.update_service("planner", [ParamDescriptor(name=n, value=1.0, type="float") for n in
                                 ("max_velocity_mps", "max_velocity_mps2", "acceptance_radius_m", "kp")]
                     + [ParamDescriptor(name="mode", value="x", type="str"),
                        ParamDescriptor(name="count", value=3, type="int"),
                        ParamDescriptor(name="enabled", value=True, type="bool")])
    names = [e.mav_name for e in t.entries]
    assert all(len(n) <= 16 for n in names) and len(set(names)) == len(names) == 6   # string not exposed
    idx, e = t.lookup("PLN_KP")
    assert t.lookup(index=idx)[1] is e and t.lookup("NOPE") is None and t.lookup(index=99) is None
    msg = t.value_msg(idx, e)
    assert msg.param_count == 6 and msg.param_index == idx


def test_param_values_bytewise():
    assert decode_value(encode_value(7, M.MAV_PARAM_TYPE_INT32), M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_INT32) == 7
    assert decode_value(encode_value(True, M.MAV_PARAM_TYPE_UINT8), M.MAV_PARAM_TYPE_UINT8, M.MAV_PARAM_TYPE_UINT8) is True
    assert struct.pack("<f", encode_value(-3, M.MAV_PARAM_TYPE_INT32)) == struct.pack("<i", -3)
    assert decode_value(2.5, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_REAL32) == 2.5
    assert decode_value(5.0, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT32) == 5   # cast-encoded
    # a float32 on the wire reaches the service as the decimal the operator typed
    f32 = struct.unpack("<f", struct.pack("<f", 1.1))[0]
    assert f32 != 1.1 and decode_value(f32, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_REAL32) == 1.1
    assert decode_value(struct.unpack("<f", struct.pack("<f", -0.3))[0], M.MAV_PARAM_TYPE_REAL32,
                        M.MAV_PARAM_TYPE_REAL32) == -0.3


# ---------------------------------------------------------------- commands


class FakeOps:
    def __init__(self):
        self.calls, self.dones = [], []

    def _rec(self, *a):
        self.calls.append(a[:-1])
        self.dones.append(a[-1])

    def arm(self, arm, force, done): self._rec("arm", arm, force, done)
    def set_mode(self, mode, done): self._rec("set_mode", mode, done)
    def mission_command(self, c, done): self._rec("mission", c, done)
    def mission_start(self, done): self._rec("start", done)
    def takeoff(self, alt, done): self._rec("takeoff", alt, done)
    def goto(self, enu, yaw, done): self._rec("goto", enu, yaw, done)
    def change_speed(self, speed, done): self._rec("speed", speed, done)


def handler():
    sent, ops = [], FakeOps()
    h = CommandHandler(sent.append, ops, HOME, position_enu=lambda: (1.0, 2.0, 3.0),
                       request_message=lambda mid, p2: M.MAV_RESULT_ACCEPTED if mid == 148 else M.MAV_RESULT_UNSUPPORTED,
                       set_interval=lambda mid, us: True, set_current=lambda s: s < 3)
    return h, sent, ops


def cmd_long(cmd, *p):
    p = list(p) + [0.0] * (7 - len(p))
    return from_gcs(M.MAVLink_command_long_message(1, 1, cmd, 0, *p))


def test_arm_acks_real_outcome_once_and_no_double_execution():
    """Issue 9 #1: one final ACK, never IN_PROGRESS (MAVSDK takes it as the outcome); a retry while
    the first runs is neither run again nor answered; a refusal comes with a STATUSTEXT reason."""
    h, sent, ops = handler()
    notes = []
    h.notify = lambda text, peer: notes.append((text, peer))
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), 0.0)
    assert ops.calls == [("arm", True, False)] and sent == []
    h.tick(0.35)
    assert sent == []                                                  # no IN_PROGRESS
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), 0.5)      # MAVSDK's retransmission
    assert len(ops.calls) == 1 and sent == [] and h.retransmissions == 1
    ops.dones[0](False, "pre-arm check failed")
    assert [m.result for m in sent] == [M.MAV_RESULT_DENIED] and sent[-1].target_system == 255
    assert notes == [("COMPONENT_ARM_DISARM denied: pre-arm check failed", (255, 190))]
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, math.nan), 0.9)      # MAVSDK leaves param2 NaN
    assert ops.calls[-1] == ("arm", True, False)
    ops.dones[-1](True, "ok")
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 21196.0), 1.0)
    assert ops.calls[-1] == ("arm", False, True)
    ops.dones[-1](True, "ok")
    assert sent[-1].result == M.MAV_RESULT_ACCEPTED
    assert M.MAV_RESULT_IN_PROGRESS not in [m.result for m in sent]


def test_mode_change_final_ack_failed_when_the_stack_does_not_answer():
    h, sent, ops = handler()
    notes = []
    h.notify = lambda text, peer: notes.append(text)
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3), 0.0)   # POSCTL
    assert ops.calls == [("set_mode", "POSCTL")]
    ops.dones[0](False, "timeout calling fmu/srv/set_mode", True)        # the call failed: FAILED
    assert sent[-1].result == M.MAV_RESULT_FAILED and notes[-1].startswith("DO_SET_MODE failed: timeout")
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3), 1.0)
    h.tick(7.0, timeout_s=5.0)                                            # nothing ever came back
    assert sent[-1].result == M.MAV_RESULT_FAILED and len(sent) == 2
    ops.dones[1](True, "late")                                            # too late: not answered twice
    assert len(sent) == 2


def test_do_change_speed_command():
    h, sent, ops = handler()
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 1.0, 3.5, -1.0), 0.0)      # ground speed 3.5 m/s
    assert ops.calls[-1] == ("speed", 3.5) and sent == []
    ops.dones[-1](True, "ok")
    assert sent[-1].command == M.MAV_CMD_DO_CHANGE_SPEED and sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 0.0, 20.0), 0.0)           # the planner refuses it
    assert ops.calls[-1] == ("speed", 20.0)
    ops.dones[-1](False, "above max")
    assert sent[-1].result == M.MAV_RESULT_DENIED
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 1.0, -2.0), 0.0)           # back to the default
    assert ops.calls[-1] == ("speed", None)
    ops.dones[-1](True, "ok")
    n = len(ops.calls)
    for p1, p2, result in ((1.0, -1.0, M.MAV_RESULT_ACCEPTED),             # no change
                           (1.0, math.nan, M.MAV_RESULT_ACCEPTED),
                           (2.0, 1.0, M.MAV_RESULT_UNSUPPORTED),            # climb speed
                           (1.0, 0.0, M.MAV_RESULT_DENIED),
                           (1.0, -3.0, M.MAV_RESULT_DENIED),
                           (9.0, 2.0, M.MAV_RESULT_DENIED)):
        h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, p1, p2), 0.0)
        assert sent[-1].result == result, (p1, p2)
    assert len(ops.calls) == n                       # none of those reached the planner


def test_command_table():
    h, sent, ops = handler()
    h.handle(cmd_long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, HOME.alt_m + 5.0), 0.0)
    assert ops.calls[-1] == ("takeoff", pytest.approx(5.0))
    h.handle(cmd_long(M.MAV_CMD_NAV_LAND), 0.0)
    assert ops.calls[-1] == ("mission", "LAND")
    h.handle(cmd_long(M.MAV_CMD_NAV_RETURN_TO_LAUNCH), 0.0)
    assert ops.calls[-1] == ("mission", "RTL")
    h.handle(cmd_long(M.MAV_CMD_MISSION_START), 0.0)
    assert ops.calls[-1] == ("start",)
    base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, base, 4, 3), 0.0)
    assert ops.calls[-1] == ("set_mode", "HOLD")
    lat, lon = HOME.projection.reproject(10.0, 0.0)
    h.handle(from_gcs(M.MAVLink_command_int_message(1, 1, M.MAV_FRAME_GLOBAL, M.MAV_CMD_DO_REPOSITION, 0, 0,
                                                    -1, 0, 0, math.nan, int(lat * 1e7), int(lon * 1e7),
                                                    HOME.alt_m + 4.0)), 0.0)
    kind, enu, yaw = ops.calls[-1]
    assert kind == "goto" and enu == pytest.approx((0.0, 10.0, 4.0), abs=0.02) and yaw is None
    for c in (M.MAV_CMD_REQUEST_PROTOCOL_VERSION, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
        h.handle(cmd_long(c, 1.0), 0.0)
        assert sent[-1].command == c and sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_REQUEST_MESSAGE, 148), 0.0)
    assert sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_REQUEST_MESSAGE, 9999), 0.0)
    assert sent[-1].result == M.MAV_RESULT_UNSUPPORTED
    for done in ops.dones:
        done(True, "ok")
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, base, 99, 0), 0.0)
    assert sent[-1].result == M.MAV_RESULT_DENIED
    h.handle(cmd_long(M.MAV_CMD_DO_FLIGHTTERMINATION, 1), 0.0)
    assert sent[-1].result == M.MAV_RESULT_UNSUPPORTED
    assert mode_from_set_mode(base, 6, 0) == "OFFBOARD"


# ---------------------------------------------------------------- telemetry


def test_telemetry_is_ned_and_geodetic_about_home():
    st = VehicleState(position_m=Vector3(x=10.0, y=20.0, z=5.0), velocity_mps=Vector3(x=1.0, y=0.0, z=0.5),
                      orientation=Quaternion.from_yaw(0.0), yaw_rad=0.0, armed=True, flight_mode="OFFBOARD",
                      landed_state=2, battery_voltage_v=15.2, battery_remaining=0.8, connected=True)
    tel = TelemetryState(HOME, vehicle=st)
    lp = tel.local_position_ned()
    assert (lp.x, lp.y, lp.z, lp.vx, lp.vz) == pytest.approx((20.0, 10.0, -5.0, 0.0, -0.5))
    att = tel.attitude()
    assert att.yaw == pytest.approx(math.pi / 2) and att.roll == pytest.approx(0.0, abs=1e-9)
    gp = tel.global_position_int()
    north, east = HOME.projection.project(gp.lat / 1e7, gp.lon / 1e7)
    assert (north, east) == pytest.approx((20.0, 10.0), abs=0.02)
    assert gp.relative_alt == 5000 and gp.alt == 15000 and gp.hdg == 9000
    hb = tel.heartbeat()
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and px4.decode(hb.custom_mode) == "OFFBOARD"
    ss = tel.sys_status()
    assert ss.voltage_battery == 15200 and ss.battery_remaining == 80
    assert tel.extended_sys_state().landed_state == 2
    assert tel.autopilot_version().capabilities == CAPABILITIES
    assert CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT and CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    # issue 9 #5: ground-station setpoints are ignored, so not advertised
    assert not CAPABILITIES & M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    hp = tel.home_position()
    assert hp.latitude == int(round(HOME.lat_deg * 1e7))


def test_scheduler_intervals():
    tel = TelemetryState(HOME)
    s = Scheduler(0.9, tel.build)
    first = {m.get_type() for m in s.due(0.0)}
    assert {"HEARTBEAT", "SYS_STATUS", "GLOBAL_POSITION_INT", "HOME_POSITION"} <= first
    assert s.due(0.5) == []
    assert s.set_interval(M.MAVLINK_MSG_ID_ATTITUDE, 100_000)
    assert [m.get_type() for m in s.due(0.6)] == ["ATTITUDE"]
    assert s.set_interval(M.MAVLINK_MSG_ID_ATTITUDE, -1)
    assert "ATTITUDE" not in {m.get_type() for m in s.due(5.0)}
    assert not s.set_interval(9999, 1000)


# ---------------------------------------------------------------- link


def test_garbage_bad_crc_and_unknown_ids_are_counted():
    p = Parser()
    good = M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(GCS)
    bad = bytearray(good)
    bad[-1] ^= 0xFF
    assert p.feed(b"\x00\xff garbage \xfd\x01") == []
    assert p.feed(bytes(bad)) == []
    assert p.feed(bytes(range(256))) == []
    assert p.feed(bytes(good[:7])) == []           # truncated frame
    unknown = bytearray(good)
    unknown[7:10] = (60000).to_bytes(3, "little")  # a message id nobody defines
    assert p.feed(bytes(unknown)) == []
    invalid = p.invalid_total
    assert invalid >= 4
    msgs = p.feed(good)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"] and p.invalid_total == invalid
    for chunk in (b"", b"\xfd", b"\xfe" * 300, bytes(1000)):
        p.feed(chunk)   # never raises


def test_udp_link_learns_the_ground_station_address():
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1)
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(2.0)
    try:
        got = []
        link.start(got.append)
        gcs.sendto(M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(GCS), link.local_address)
        deadline = time.monotonic() + 2.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got and link.remote == gcs.getsockname()
        link.send(TelemetryState(HOME).heartbeat())
        data, _ = gcs.recvfrom(1000)
        (hb,) = Parser().feed(data)
        assert hb.get_type() == "HEARTBEAT" and hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    finally:
        link.close()
        gcs.close()


def test_ftp_is_nakked():
    req = from_gcs(M.MAVLink_file_transfer_protocol_message(0, 1, 1, [7, 0, 0, 4] + [0] * 247))
    nak = ftp.nak(req, ftp.ERR_FILE_NOT_FOUND)
    assert nak.payload[3] == 129 and nak.payload[5] == 4 and nak.payload[0] == 8 and nak.target_system == 255


# ---------------------------------------------------------------- waypoint altitude, plan id, one upload at a time


def from_mav(mav, msg):
    (m,) = Parser().feed(msg.pack(mav))
    return m


class ConvertingLoader:
    """Like gcs's _load: an item the conversion refuses refuses the upload with its result."""

    def __call__(self, items, done):
        try:
            convert_items(items, HOME)
        except MissionConversionError as e:
            done(False, str(e), e.result)
            return
        done(True, "ok", M.MAV_MISSION_ACCEPTED)


def takeoff_item(seq, alt=4.0):
    return Item(seq=seq, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                x=HOME.lat_deg, y=HOME.lon_deg, z=alt, param4=math.nan)


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
    # issue 8 #5: an AMSL item at (or below) home altitude is refused like a relative one, naming it;
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


def test_statustext_chunks_long_texts():
    assert len(statustext(M.MAV_SEVERITY_INFO, "short")) == 1
    chunks = statustext(M.MAV_SEVERITY_CRITICAL, "x" * 120, 9)
    assert [(c.id, c.chunk_seq, len(c.text)) for c in chunks] == [(9, 0, 50), (9, 1, 50), (9, 2, 20)]
    chunks = statustext(M.MAV_SEVERITY_CRITICAL, "y" * 100, 0)   # a multiple of 50: an empty last chunk
    assert [(c.id, c.chunk_seq, len(c.text)) for c in chunks] == [(1, 0, 50), (1, 1, 50), (1, 2, 0)]
    mav = make_mav(1, 1)
    assert [Parser().feed(c.pack(mav))[0].chunk_seq for c in chunks] == [0, 1, 2]


def test_plan_id_in_mission_current_ack_and_count():
    p, sent = proto()
    assert p.plan_id == 0 and plan_id([]) == 0
    ack = upload(p, sent, square())
    pid = p.plan_id
    assert pid != 0 and ack.opaque_id == pid
    mav = make_mav(1, 1)
    assert extension_fields(from_mav(mav, ack))["opaque_id"] == pid      # as a ground station parses it
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, 0)), 1.0)
    count = from_mav(mav, sent[-1])
    assert count.count == 4 and extension_fields(count)["opaque_id"] == pid
    p.handle(from_gcs(M.MAVLink_mission_ack_message(1, 1, 0, 0)), 1.0)

    tel = TelemetryState(HOME, mission_seq=2, mission_total=4, mission_id=pid)
    mc = from_mav(mav, tel.mission_current())
    assert (mc.seq, mc.total) == (2, 4)                                   # stock pymavlink still reads it
    assert extension_fields(mc) == {"seq": 2, "total": 4, "mission_state": M.MISSION_STATE_NOT_STARTED,
                                    "mission_mode": 0, "mission_id": pid, "fence_id": 0, "rally_points_id": 0}
    assert extension_fields(from_mav(mav, TelemetryState(HOME).mission_current()))["mission_id"] == 0

    upload(p, sent, square())                 # the same plan again: the same id
    assert p.plan_id == pid
    upload(p, sent, square(alt=6.0))          # another plan: another id
    assert p.plan_id not in (0, pid)
    p.handle(from_gcs(M.MAVLink_mission_clear_all_message(1, 1, 0)), 2.0)
    assert p.plan_id == 0


def test_one_upload_at_a_time_between_ground_stations():
    other = make_mav(246, 190)
    p, sent = proto()
    pts = square(2)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_REQUEST_INT" and sent[-1].target_system == 255
    n = len(sent)
    # another ground station meanwhile: its upload, download and clear are refused, its items ignored
    p.handle(from_mav(other, M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_DENIED
    assert sent[-1].target_system == 246
    p.handle(from_mav(other, M.MAVLink_mission_request_list_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_DENIED and sent[-1].target_system == 246
    p.handle(from_mav(other, M.MAVLink_mission_clear_all_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_DENIED
    lat, lon, alt = pts[0]
    p.handle(from_mav(other, M.MAVLink_mission_item_int_message(
        1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
        int(lat * 1e7), int(lon * 1e7), alt, 0)), 0.0)
    p.handle(from_mav(other, M.MAVLink_mission_ack_message(1, 1, M.MAV_MISSION_OPERATION_CANCELLED, 0)), 0.0)
    assert p.errors["busy"] == 3 and p.errors["item_from_other_peer"] == 1
    assert p.transfer is not None and p.transfer.expected == 0 and len(sent) == n + 3
    # the first one finishes its upload undisturbed; then the other may download it
    for i, (lat, lon, alt) in enumerate(pts):
        p.handle(item_int(i, lat, lon, alt), 0.1)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_ACCEPTED and len(p.items) == 2
    p.handle(from_mav(other, M.MAVLink_mission_request_list_message(1, 1, 0)), 0.2)
    assert sent[-1].get_type() == "MISSION_COUNT" and sent[-1].count == 2 and sent[-1].target_system == 246


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
    """Issue 9 #2: a trailing NAV_LAND without a position is reached once landed, then COMPLETE
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


# ---------------------------------------------------------------- several ground stations


class FakeClock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def udp_peer() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.02)
    return s


def drain(sock: socket.socket, wait_s: float = 0.3, until: int = 0) -> list:
    """The MAVLink messages arriving on `sock` within wait_s (sooner once `until` have arrived)."""
    out, parser = [], Parser()
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and not (until and len(out) >= until):
        try:
            data, _ = sock.recvfrom(65535)
        except socket.timeout:
            continue
        out += parser.feed(data)
    return out


def types(msgs) -> list[str]:
    return [m.get_type() for m in msgs]


def poll(pred, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


def test_several_ground_stations_telemetry_to_all_alive_replies_to_the_asker():
    clock = FakeClock()
    initial, a, b = udp_peer(), udp_peer(), udp_peer()
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", initial.getsockname()[1], 1, 1, timeout_s=3.0, clock=clock)
    mav_a, mav_b = make_mav(255, 190), make_mav(246, 190)
    hb_gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 4)
    hb = TelemetryState(HOME).heartbeat()

    def on_message(m):
        if m.get_type() == "PARAM_REQUEST_READ":   # answered at once, as gcs does: to the asker only
            link.send(M.MAVLink_param_value_message(b"GCS_X", 1.0, M.MAV_PARAM_TYPE_REAL32, 1, 0))

    def hb_from(sock, mav):
        n = link.parser.received
        sock.sendto(hb_gcs.pack(mav), link.local_address)
        poll(lambda: link.parser.received > n)

    try:
        link.start(on_message)
        link.send(hb)                                  # nobody heard yet: the initial address
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]
        assert link.destinations() == [initial.getsockname()] and not link.alive()

        hb_from(a, mav_a)                              # A talks: telemetry to A, and still to the
        link.send(hb)                                  # initial address (a listen-only station, issue 9 #4)
        assert types(drain(a, until=1)) == ["HEARTBEAT"] and types(drain(initial, until=1)) == ["HEARTBEAT"]
        hb_from(b, mav_b)                              # B too: telemetry to both
        assert {p.address for p in link.alive()} == {a.getsockname(), b.getsockname()}
        link.send(hb)
        assert types(drain(a, until=1)) == ["HEARTBEAT"] and types(drain(b, until=1)) == ["HEARTBEAT"]
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]

        # B asks: only B gets the answer
        b.sendto(M.MAVLink_param_request_read_message(1, 1, b"GCS_X", -1).pack(mav_b), link.local_address)
        assert types(drain(b, until=1)) == ["PARAM_VALUE"] and drain(a, 0.1) == [] and drain(initial, 0.1) == []
        # a later reply with a target goes where that target spoke from
        link.send(M.MAVLink_command_ack_message(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 255, 190))
        assert types(drain(a, until=1)) == ["COMMAND_ACK"] and drain(b, 0.1) == []
        link.send(M.MAVLink_mission_ack_message(246, 0, 0, 0))         # target_component 0: that system
        assert types(drain(b, until=1)) == ["MISSION_ACK"] and drain(a, 0.1) == []
        for m in statustext(M.MAV_SEVERITY_CRITICAL, "to B"):           # explicit peer
            link.send(m, peer=(246, 190))
        assert types(drain(b, until=1)) == ["STATUSTEXT"] and drain(a, 0.1) == []
        link.send(M.MAVLink_param_value_message(b"GCS_X", 2.0, M.MAV_PARAM_TYPE_REAL32, 1, 0), broadcast=True)
        assert types(drain(a, until=1)) == ["PARAM_VALUE"] and types(drain(b, until=1)) == ["PARAM_VALUE"]
        assert types(drain(initial, until=1)) == ["PARAM_VALUE"]

        # A goes silent: after the timeout only B (still beating) gets telemetry
        clock.t += 2.0
        hb_from(b, mav_b)
        clock.t += 1.5                                 # A's heartbeat 3.5 s old, B's 1.5 s
        assert [p.address for p in link.alive()] == [b.getsockname()]
        link.send(hb)
        assert types(drain(b, until=1)) == ["HEARTBEAT"] and drain(a, 0.1) == []
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]
        # nobody left: the initial address and the last ground station heard
        clock.t += 10.0
        assert not link.alive() and link.destinations() == [initial.getsockname(), b.getsockname()]
        link.send(hb)
        assert types(drain(initial, until=1)) == ["HEARTBEAT"] and types(drain(b, until=1)) == ["HEARTBEAT"]
        assert drain(a, 0.1) == []
    finally:
        link.close()
        for s in (initial, a, b):
            s.close()


# ---------------------------------------------------------------- MAVLink 2 signing

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(32)


def test_signing_key_from_hex_raw_bytes_or_file(tmp_path):
    assert parse_signing_key(KEY.hex()) == KEY
    assert parse_signing_key(f"  {KEY.hex().upper()}\n") == KEY
    assert parse_signing_key(KEY) == KEY
    for bad in ("abc", "zz" * 32, KEY.hex()[:-2], KEY[:31], KEY.hex() + "00"):
        with pytest.raises(ValueError) as e:
            parse_signing_key(bad)
        assert KEY.hex()[:8] not in str(e.value) and "zz" not in str(e.value)   # never echoes the key
    f = tmp_path / "gcs.key"
    f.write_text(KEY.hex() + "\n")
    f.chmod(0o600)
    assert load_signing_key(f) == (KEY, False)
    f.chmod(0o644)
    assert load_signing_key(f) == (KEY, True)                 # readable by others: gcs warns
    with pytest.raises(ValueError, match="signing key file"):
        load_signing_key(tmp_path / "missing.key")


def ground_station(port: int, system_id: int, key: bytes | None = None, link_id: int = 0):
    """A pymavlink ground station (mavutil), signing with `key` if given."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system_id, source_component=190,
                                      dialect="common")
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True, link_id=link_id)
    return conn


def recv_type(conn, mtype: str, timeout_s: float = 2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = conn.recv_match(type=mtype, blocking=True, timeout=0.05)
        if m is not None:
            return m
    return None


def signed_frame(msg, system_id: int, key: bytes, link_id: int, timestamp: int) -> bytes:
    mav = make_mav(system_id, 190)
    mav.signing.secret_key, mav.signing.sign_outgoing = key, True
    mav.signing.link_id, mav.signing.timestamp = link_id, timestamp
    return msg.pack(mav)


def test_signing_signed_ground_station_works_unsigned_and_wrongly_signed_are_dropped_and_counted():
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1, signing_key=KEY, signing_link_id=7)
    port = link.local_address[1]
    got = []

    def on_message(m):
        got.append((m.get_srcSystem(), m.get_type()))
        if m.get_type() == "PARAM_REQUEST_READ":
            link.send(M.MAVLink_param_value_message(b"GCS_X", 1.0, M.MAV_PARAM_TYPE_REAL32, 1, 0))

    good = ground_station(port, 255, KEY)
    plain = ground_station(port, 254)
    wrong = ground_station(port, 253, OTHER_KEY)
    raw = udp_peer()
    hb_gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 4)
    try:
        link.start(on_message)
        for c in (good, plain, wrong):
            c.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            c.mav.param_request_read_send(1, 1, b"GCS_X", -1)
        poll(lambda: len(got) >= 2 and link.parser.invalid["unsigned"] >= 2
             and link.parser.invalid["bad_signature"] >= 2)
        assert got == [(255, "HEARTBEAT"), (255, "PARAM_REQUEST_READ")]
        assert [p.system_id for p in link.alive()] == [255]

        # the signed ground station gets its answer, signed with our link id and a current timestamp
        # (its pymavlink, holding the key, would drop anything unsigned or wrongly signed)
        pv = recv_type(good, "PARAM_VALUE")
        assert pv is not None and pv._signed and pv._link_id == 7
        tlow, thigh = struct.unpack("<IH", bytes(pv.get_msgbuf())[-12:-6])
        assert abs((tlow + (thigh << 32)) - signing_timestamp()) < 5 * 100_000
        assert good.mav.signing.goodsig_count >= 1 and good.mav.signing.badsig_count == 0
        link.send(TelemetryState(HOME).heartbeat())             # telemetry: to the signed one only
        assert recv_type(good, "HEARTBEAT") is not None
        assert plain.recv_match(blocking=True, timeout=0.3) is None
        assert wrong.recv_match(blocking=True, timeout=0.1) is None

        # replay protection: a signed frame is accepted once; a copy, or a new stream from long
        # ago, is refused
        now = signing_timestamp()
        frame = signed_frame(hb_gcs, 252, KEY, 3, now)
        for _ in range(2):
            raw.sendto(frame, link.local_address)
        raw.sendto(signed_frame(hb_gcs, 251, KEY, 3, now - 120 * 100_000), link.local_address)
        poll(lambda: link.parser.invalid["replayed"] == 1 and link.parser.invalid["stale_timestamp"] == 1)
        assert got[-1] == (252, "HEARTBEAT") and got.count((252, "HEARTBEAT")) == 1

        # a wrongly signed frame with a far-future timestamp on the good station's stream does not
        # lock it out (pymavlink alone would record that timestamp before checking the signature)
        raw.sendto(signed_frame(hb_gcs, 255, OTHER_KEY, 0, now + 3600 * 100_000), link.local_address)
        poll(lambda: link.parser.invalid["bad_signature"] >= 3)
        n = len(got)
        good.mav.param_request_read_send(1, 1, b"GCS_X", -1)
        poll(lambda: len(got) > n)
        assert got[-1] == (255, "PARAM_REQUEST_READ")
        assert link.parser.signing_rejected == link.parser.invalid_total >= 7
    finally:
        link.close()
        for c in (good, plain, wrong):
            c.close()
        raw.close()


def test_px4_names_map_to_the_owning_services_parameters():
    """Issue 9 #3: PX4 names read the services' live values, exist only while an owner answers,
    and a geofence name covers both mission and safety; fixed answers are read-only."""
    from aeroperception.services.gcs.params import ALIAS_SERVICE
    t = ParamTable(["planner", "mission", "gcs"])
    assert {"sim", "safety"} <= set(t.sources)            # read for their aliases, not exposed natively
    names = lambda: {e.mav_name for e in t.entries}       # noqa: E731
    assert names() == {"COM_RC_IN_MODE", "NAV_DLL_ACT"}   # constants only, nobody answered yet
    t.update_service("mission", [ParamDescriptor(name="takeoff_altitude_m", value=3.0, min=0.5, max=120.0)])
    t.update_service("planner", [ParamDescriptor(name="max_velocity_mps", value=2.0, default=2.0, min=0.1, max=15.0),
                                 ParamDescriptor(name="acceptance_radius_m", value=0.5)])
    assert {"MIS_TAKEOFF_ALT", "MPC_XY_VEL_MAX", "NAV_ACC_RAD"} <= names()
    assert "GF_MAX_HOR_DIST" not in names() and "GF_ACTION" not in names() and "RTL_RETURN_ALT" not in names()
    _, e = t.lookup("MPC_XY_VEL_MAX")
    assert (e.service, e.value, e.min, e.max, e.targets) == (ALIAS_SERVICE, 2.0, 0.1, 15.0, (("planner", "max_velocity_mps"),))
    t.set_value("planner", "max_velocity_mps", 3.5)        # a confirmed set: native and alias agree
    assert t.lookup("MPC_XY_VEL_MAX")[1].value == 3.5 and t.find("planner", "max_velocity_mps")[1].value == 3.5

    fence = [ParamDescriptor(name="geofence_radius_m", value=500.0, min=1.0, max=100000.0),
             ParamDescriptor(name="geofence_max_altitude_m", value=120.0, min=1.0, max=10000.0)]
    t.update_service("safety", fence + [ParamDescriptor(name="geofence_action", value=2, type="int")])
    _, gf = t.lookup("GF_MAX_HOR_DIST")
    assert gf.targets == (("safety", "geofence_radius_m"),) and gf.value == 500.0
    t.update_service("mission", [ParamDescriptor(name="takeoff_altitude_m", value=3.0)] + fence)
    assert t.lookup("GF_MAX_HOR_DIST")[1].targets == (("mission", "geofence_radius_m"), ("safety", "geofence_radius_m"))
    _, act = t.lookup("GF_ACTION")
    assert act.ptype == M.MAV_PARAM_TYPE_INT32 and act.value == 2
    t.update_service("sim", [ParamDescriptor(name="RTL_RETURN_ALT", value=60.0)])
    assert t.lookup("RTL_RETURN_ALT")[1].value == 60.0
    _, dll = t.lookup("NAV_DLL_ACT")
    assert dll.value == 1 and dll.readonly and t.lookup("COM_RC_IN_MODE")[1].value == 4
    assert not any(e.service == "sim" for e in t.entries)  # the sim's own names are not exposed
    idx, e = t.lookup("MIS_TAKEOFF_ALT")
    assert t.value_msg(idx, e).param_id == "MIS_TAKEOFF_ALT" and t.lookup(index=idx)[1] is e


def test_mission_speed_ends_with_the_mission():
    """Issue 9 #7: a speed set for a mission is restored when the mission completes, lands, is
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


def test_safety_status_fence_bits_and_statustext_once_per_change():
    """Issue 9 #8: no safety/status -> no fence in SYS_STATUS; then present/enabled/healthy from
    geofence_status; warnings and errors -> STATUSTEXT once when they appear, INFO when cleared."""
    from aeroperception.schemas import SafetyStatus
    from aeroperception.services.gcs.safety_relay import SafetyRelay
    fence = M.MAV_SYS_STATUS_GEOFENCE
    tel = TelemetryState(HOME)
    s = tel.sys_status()
    assert not (s.onboard_control_sensors_present | s.onboard_control_sensors_enabled) & fence
    tel.safety, tel.safety_rx_s = SafetyStatus(distance_to_geofence_m=50.0), time.monotonic()
    s = tel.sys_status()
    assert s.onboard_control_sensors_present & s.onboard_control_sensors_enabled & s.onboard_control_sensors_health & fence
    tel.safety = SafetyStatus(geofence_status=SafetyStatus.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0)
    assert tel.fence_bits() == (fence, fence, 0)                      # breached: present, enabled, unhealthy
    tel.safety = SafetyStatus(distance_to_geofence_m=None)
    assert tel.fence_bits() == (fence, 0, fence)                      # safety runs without a fence
    assert tel.fence_bits(now_s=tel.safety_rx_s + 10.0) == (0, 0, 0)  # safety gone quiet: unknown

    relay = SafetyRelay()
    st = SafetyStatus(active_warnings=["battery low"], active_errors=["fmu dead"])
    assert relay.update(st) == [(M.MAV_SEVERITY_CRITICAL, "Safety: fmu dead"), (M.MAV_SEVERITY_WARNING, "Safety: battery low")]
    assert relay.update(st) == []                                      # repeated at 1 Hz: once only
    st = SafetyStatus(active_warnings=["battery low"], active_errors=["fmu dead", "geofence breached"],
                      safety_level=SafetyStatus.LEVEL_EMERGENCY)
    assert relay.update(st) == [(M.MAV_SEVERITY_EMERGENCY, "Safety: geofence breached")]
    assert relay.update(SafetyStatus()) == [(M.MAV_SEVERITY_INFO, "Safety: cleared: battery low"),
                                            (M.MAV_SEVERITY_INFO, "Safety: cleared: fmu dead"),
                                            (M.MAV_SEVERITY_INFO, "Safety: cleared: geofence breached")]


def test_companion_identity_heartbeat_is_an_onboard_computer():
    """Issue 9 #6: in the vehicle profile gcs is not a second vehicle."""
    hb = TelemetryState(HOME, companion=True).heartbeat()
    assert (hb.type, hb.autopilot, hb.base_mode, hb.custom_mode) == (M.MAV_TYPE_ONBOARD_CONTROLLER,
                                                                     M.MAV_AUTOPILOT_INVALID, 0, 0)
    hb = TelemetryState(HOME).heartbeat()
    assert (hb.type, hb.autopilot) == (M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4)
