"""The home gcs converts about: PX4's projection about the local origin, the flight controller's
home once reported (telemetry, mission items and commands about it), a change held back while a
mission upload is under way."""
from __future__ import annotations

import math

import pytest
from gcs_support import HOME, FakeOps, Loader, cmd_long, from_gcs, item_int, proto, square, upload
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import HomePosition, Vector3, VehicleState
from aeroperception.services.gcs.commands import CommandHandler
from aeroperception.services.gcs.home import Home, HomeTracker, home_from_msg, mission_needs_upload_again, origin_shift_m
from aeroperception.services.gcs.mission_items import Item, convert_items, mission_to_items
from aeroperception.services.gcs.telemetry import TelemetryState
from aeroperception.services.lib.geo import MapProjection


def test_global_relative_to_enu_about_home_and_back():
    lat, lon = HOME.projection.reproject(20.0, -5.0)   # 20 m north, 5 m west
    x, y, z = HOME.to_enu(lat, lon, 7.0)
    assert (x, y, z) == pytest.approx((-5.0, 20.0, 7.0), abs=1e-3)
    back = HOME.to_geodetic(x, y, z)
    assert back == pytest.approx((lat, lon, 7.0), abs=1e-9)


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


def test_a_mission_needs_uploading_again_only_when_home_moved_more_than_half_a_metre():
    home = Home(*ZURICH)
    north_0_3m = MapProjection(*ZURICH[:2]).reproject(north_m=0.3, east_m=0.0)
    north_2m = MapProjection(*ZURICH[:2]).reproject(north_m=2.0, east_m=0.0)
    assert not mission_needs_upload_again(home, Home(*north_0_3m, ZURICH[2]))
    assert mission_needs_upload_again(home, Home(*north_2m, ZURICH[2]))
    assert mission_needs_upload_again(home, Home(ZURICH[0], ZURICH[1], ZURICH[2] + 1.0))     # origin 1 m higher
    assert not mission_needs_upload_again(home, Home(ZURICH[0], ZURICH[1], ZURICH[2] + 1.0, (0.0, 0.0, 1.0)))
