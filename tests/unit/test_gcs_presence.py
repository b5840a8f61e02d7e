"""gcs ground-station presence: only ground stations count, no verdict before a full
timeout after start, and a stall (SIGSTOP) is judged from packets actually received."""
from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as M  # noqa: E402

import pytest  # noqa: E402
from gcs_support import Log  # noqa: E402

from aeroperception.services.gcs.link import Parser, UdpLink, make_mav  # noqa: E402
from aeroperception.services.gcs.presence import (  # noqa: E402
    GroundStationFilter, LinkVerdict, ListeningClock, Presence,
)


class Raw:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def heartbeat(mav_type: int, sysid: int = 255):
    data = M.MAVLink_heartbeat_message(mav_type, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(make_mav(sysid, 190))
    return Parser().feed(data)[0]


def test_only_gcs_heartbeats_or_configured_ids_are_ground_stations():
    f = GroundStationFilter.from_param("42, 7")
    assert f(heartbeat(M.MAV_TYPE_GCS))
    assert not f(heartbeat(M.MAV_TYPE_QUADROTOR))             # a stray vehicle heartbeat
    assert not f(heartbeat(M.MAV_TYPE_ONBOARD_CONTROLLER, 9))
    assert f(heartbeat(M.MAV_TYPE_ONBOARD_CONTROLLER, 42))    # configured id
    with pytest.raises(ValueError, match="gcs_system_ids"):
        GroundStationFilter.from_param("255,abc")


def test_stray_heartbeat_makes_no_ground_station_and_no_link():
    raw = Raw()
    clock = ListeningClock(source=raw)
    clock.tick()
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1, timeout_s=3.5, clock=clock,
                   is_ground_station=GroundStationFilter())
    try:
        stray = M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, 0, 0, 0, 3).pack(make_mav(7, 1))
        link.handle_datagram(stray, ("127.0.0.1", 5000))
        assert link.alive() and not link.ground_stations()   # a telemetry destination, not a ground station
        gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(make_mav(255, 190))
        link.handle_datagram(gcs, ("127.0.0.1", 5001))
        assert [p.address for p in link.ground_stations()] == [("127.0.0.1", 5001)]
    finally:
        link.close()


def test_no_verdict_before_a_full_timeout_after_start():
    v = LinkVerdict(3.5, start_s=10.0)
    assert v.update(10.0, False) is None
    assert v.update(13.4, False) is None          # still listening: a restarted gcs says nothing
    assert v.update(13.5, False) is False         # listened the whole timeout: nobody there
    v = LinkVerdict(3.5, start_s=10.0)
    assert v.update(11.0, True) is True           # heard: up at once
    assert v.update(12.0, False) is False         # (ages are judged by the caller) lost


def test_a_stall_does_not_count_as_silence():
    """SIGSTOP for 15 s: heartbeats queued in the socket meanwhile are read right after the resume;
    the stall is not part of any heartbeat's age, so the link never goes lost."""
    raw = Raw(100.0)
    clock = ListeningClock(stall_s=1.0, source=raw)
    clock.tick()
    hb = clock()                                   # last heartbeat before the stall
    raw.t += 0.05
    clock.tick()
    raw.t += 15.0                                  # stopped: no tick, no receive
    assert clock() - hb <= 1.05 + 1e-9             # a packet read before the timer noticed: not "15 s old"
    assert clock.tick() == pytest.approx(14.0)     # the timer notices: 14 s taken out
    assert clock() - hb == pytest.approx(1.05)
    for _ in range(40):                            # then listening time runs normally again
        raw.t += 0.05
        clock.tick()
    assert clock() - hb == pytest.approx(3.05)
    assert clock.stalls == 1


def test_a_ground_station_gone_during_a_stall_is_lost_a_full_timeout_after_the_resume():
    raw = Raw(0.0)
    clock = ListeningClock(stall_s=1.0, source=raw)
    clock.tick()
    v = LinkVerdict(3.5, clock())
    last_hb = clock()
    assert v.update(clock(), True) is True
    raw.t += 15.0                                  # stalled; the station died meanwhile (nothing queued)
    clock.tick()
    ages = []
    while v.update(clock(), clock() - last_hb <= 3.5):
        raw.t += 0.05
        clock.tick()
        ages.append(raw.t)
    assert 15.0 + 2.4 < ages[-1] < 15.0 + 2.6      # 1 s of the stall + 2.5 s of listening after it


def test_presence_says_each_change_of_the_verdict_once_and_logs_every_station():
    raw = Raw(0.0)
    clock = ListeningClock(source=raw)
    clock.tick()
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1, timeout_s=2.0, clock=clock,
                   is_ground_station=GroundStationFilter())
    log = Log()
    presence = Presence(link, 2.0, clock(), log)
    gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(make_mav(255, 190))

    def listen_until(t: float) -> None:          # the 20 Hz timer runs: listening time passes
        while raw.t < t - 1e-9:
            raw.t += 0.05
            clock.tick()
    try:
        assert presence.update(clock()) is False and presence.verdict.connected is None   # still listening
        listen_until(2.0)
        assert presence.update(clock()) is True and log.events == ["gcs_link_none"]      # nobody: said once
        assert presence.update(clock()) is False
        link.handle_datagram(gcs, ("127.0.0.1", 5001))
        assert presence.heard(255, clock()) is True and presence.connected and presence.system_id == 255
        assert log.events[1:] == ["gcs_heard", "gcs_link_up"] and presence.addresses() == "127.0.0.1:5001"
        listen_until(4.5)                                                                 # silent for 2.5 s
        assert presence.update(clock()) is True and not presence.connected
        assert log.events[3:] == ["gcs_lost", "gcs_link_lost"] and presence.alive == set()
    finally:
        link.close()
