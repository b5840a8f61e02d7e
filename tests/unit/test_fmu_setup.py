"""fmu's link set-up (services/fmu/setup.py) and stream timing (timing.py), without sockets or
Zenoh: what is asked of the flight controller, when, and again after it rebooted."""
from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.fmu.config import FmuConfig
from aeroperception.services.fmu import contract
from aeroperception.services.fmu.setup import STREAMS_HZ, LinkSetup
from aeroperception.services.fmu.timing import StreamTiming
from aeroperception.services.runtime.config import build, check_covers

INTERVAL, REQUEST = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE
HOME, ORIGIN, TRUTH = (mavlink.MAVLINK_MSG_ID_HOME_POSITION, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
                       mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION)


def requested(commands) -> list[tuple[int, int]]:
    return [(c.command, int(c.params[0])) for c in commands]


def test_the_first_heartbeat_asks_for_every_stream_and_home_later_ones_nothing():
    s = LinkSetup(reboot_gap_s=2.0, ground_truth_rate_hz=100.0, home_request_period_s=10.0)
    first = s.on_heartbeat(0.0, home_known=False)
    assert requested(first.commands) == [(INTERVAL, m) for m in [*STREAMS_HZ, TRUTH]] + [(REQUEST, HOME)]
    assert first.rebooted == "" and s.counters == {"reboots_detected": 0, "link_setups": 1}
    assert first.commands[0].params7() == [mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1e6 / 50, 0, 0, 0, 0, 0]
    assert s.on_heartbeat(1.0, home_known=False).commands == []


def test_no_ground_truth_stream_is_asked_at_rate_zero_nor_home_once_known():
    s = LinkSetup(2.0, ground_truth_rate_hz=0.0, home_request_period_s=10.0)
    assert requested(s.on_heartbeat(0.0, home_known=True).commands) == [(INTERVAL, m) for m in STREAMS_HZ]


def test_a_heartbeat_gap_or_boot_time_going_back_redoes_the_set_up_once_a_second():
    s = LinkSetup(reboot_gap_s=2.0, ground_truth_rate_hz=0.0, home_request_period_s=10.0)
    s.on_boot_time(50_000, 0.0, True)
    s.on_heartbeat(0.0, home_known=True)
    again = s.on_heartbeat(3.0, home_known=True)                 # 3 s without a heartbeat
    assert again.rebooted == "no heartbeat for 3.0 s"
    assert requested(again.commands) == [(INTERVAL, m) for m in STREAMS_HZ] + [(REQUEST, HOME)]
    assert s.on_boot_time(1_000, 3.5, True).commands == []       # the same reboot, within a second
    later = s.on_boot_time(500, 4.5, True)
    assert later.rebooted == "" and later.commands == []         # went back by less than the tolerance
    assert s.on_boot_time(100_000, 5.0, True).commands == [] and s.on_boot_time(10, 5.0, True).rebooted
    assert s.counters == {"reboots_detected": 2, "link_setups": 3}


def test_boot_time_before_the_first_heartbeat_redoes_nothing():
    s = LinkSetup(2.0, 0.0, 10.0)
    s.on_boot_time(50_000, 0.0, False)
    assert s.on_boot_time(10, 0.1, False).commands == [] and not s.streams_requested


def test_home_is_asked_again_every_period_and_the_origin_once_a_second():
    s = LinkSetup(2.0, 0.0, home_request_period_s=10.0)
    assert s.home_due(0.0) == []                      # not before the link is set up
    s.on_heartbeat(0.0, home_known=False)             # asks for home at 0
    assert s.home_due(9.9) == [] and requested(s.home_due(10.0)) == [(REQUEST, HOME)]
    assert requested(s.origin_missing(0.0)) == [(REQUEST, ORIGIN)]
    assert s.origin_missing(1.0) == [] and requested(s.origin_missing(1.01)) == [(REQUEST, ORIGIN)]


def test_camera_frames_are_timed_against_the_imu_before_them_and_vio_latency_reported():
    t = StreamTiming()
    assert math.isnan(t.on_image(5_000_000)) and t.values() == {"camera_imu_dt_p50_ms": pytest.approx(math.nan, nan_ok=True),
                                                                "camera_imu_dt_max_ms": pytest.approx(math.nan, nan_ok=True)}
    t = StreamTiming()
    for stamp in (10_000_000, 15_000_000, 20_000_000):
        t.on_imu(stamp)
    assert t.on_image(16_000_000) == pytest.approx(1.0)      # 1 ms after the 15 ms sample
    assert t.on_image(8_000_000) == pytest.approx(-2.0)      # before every sample: against the first
    t.on_vio_sent(0.030)
    t.on_vio_sent(0.050)
    assert t.values() == {"camera_imu_dt_p50_ms": -0.5, "camera_imu_dt_max_ms": 2.0,
                          "vio_age_p50_ms": 40.0, "vio_age_max_ms": 50.0}


def test_the_config_references_every_parameter_and_a_bad_origin_fails_the_build():
    check_covers(FmuConfig, contract.PARAMS, "fmu")
    assert build(FmuConfig, contract.PARAMS).global_origin is None
    assert build(FmuConfig, {**{p.name: p.default for p in contract.PARAMS}, "global_origin": "47.4,8.5,489"}
                 ).global_origin == (47.4, 8.5, 489.0)
    with pytest.raises(ValueError, match="global_origin"):
        build(FmuConfig, {**{p.name: p.default for p in contract.PARAMS}, "global_origin": "47.4,8.5"})
