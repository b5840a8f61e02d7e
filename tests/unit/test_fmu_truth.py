"""fmu's ground truth of a simulated FC (services/fmu/truth.py): HIL_STATE_QUATERNION -> ENU/FLU
VehicleState about the FC's local origin, and FcClock: FC boot time -> this host's clock, the
stamps of the FC's IMU and of the (untimed) ground truth on one clock."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.fmu.truth import FcClock, ground_truth_from_mavlink, origin_from_mavlink
from aeroperception.services.lib.geo import MapProjection

ORIGIN = (47.3977459, 8.5455930, 489.056)      # PX4 SIH's EKF2 origin, as GPS_GLOBAL_ORIGIN reported it


def hil(lat_deg, lon_deg, alt_m, q_ned_frd=(1.0, 0, 0, 0), v_ned_cmps=(0, 0, 0), rates_frd=(0.0, 0.0, 0.0)):
    """A real pymavlink HIL_STATE_QUATERNION as PX4 sends it (time_usec 0)."""
    return mavlink.MAVLink_hil_state_quaternion_message(
        0, list(q_ned_frd), *rates_frd, round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_m * 1e3),
        *v_ned_cmps, 0, 0, 0, 0, 0)


def at(north_m, east_m, up_m, **kw):
    lat, lon = MapProjection(ORIGIN[0], ORIGIN[1]).reproject(north_m, east_m)
    return hil(lat, lon, ORIGIN[2] + up_m, **kw)


def test_position_is_enu_about_the_fc_local_origin():
    s = ground_truth_from_mavlink(at(3.0, 10.0, 5.0), ORIGIN, 123)
    np.testing.assert_allclose(s.position_m.to_array(), [10.0, 3.0, 5.0], atol=0.012)   # degE7: ~1 cm
    assert s.header.stamp_ns == 123 and s.header.frame_id == "map" and s.estimator_name == "ground_truth"
    assert s.connected and s.confidence == 1.0


def test_velocity_attitude_and_rates_are_enu_flu():
    half = math.sqrt(0.5)
    # NED/FRD yaw 90 deg (facing East), moving North 2 m/s and climbing 1 m/s, yawing right 0.3 rad/s
    s = ground_truth_from_mavlink(at(0, 0, 1, q_ned_frd=(half, 0, 0, half), v_ned_cmps=(200, 0, -100),
                                     rates_frd=(0.1, 0.2, 0.3)), ORIGIN, 0)
    np.testing.assert_allclose(s.velocity_mps.to_array(), [0.0, 2.0, 1.0])
    assert s.yaw_rad == pytest.approx(0.0, abs=1e-6)                    # facing East = ENU yaw 0
    np.testing.assert_allclose(s.orientation.to_array(), [1, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(s.angular_velocity_radps.to_array(), [0.1, -0.2, -0.3], rtol=1e-6)


def test_sih_attitude_with_negative_w_is_the_same_rotation_with_w_positive():
    s = ground_truth_from_mavlink(at(0, 0, 0, q_ned_frd=(-1.0, 0, 0, 0)), ORIGIN, 0)   # what SIH sends at rest
    q = s.orientation.to_array()
    assert q[0] > 0
    assert s.yaw_rad == pytest.approx(math.pi / 2)                       # facing North


def test_status_fields_come_from_the_fc_telemetry():
    s = ground_truth_from_mavlink(at(0, 0, 0), ORIGIN, 0, armed=True, flight_mode="OFFBOARD", landed_state=2)
    assert s.armed and s.flight_mode == "OFFBOARD" and s.landed_state == 2


@pytest.mark.parametrize("origin,msg", [
    (None, at(0, 0, 0)),                                   # no local origin yet: cannot place it
    (ORIGIN, hil(0, 0, 0)),                                # 0/0: the simulator has not started
    (ORIGIN, at(0, 0, 0, q_ned_frd=(0, 0, 0, 0))),         # no attitude
    (ORIGIN, at(0, 0, 0, q_ned_frd=(float("nan"), 0, 0, 0))),
])
def test_unusable_samples_are_none(origin, msg):
    assert ground_truth_from_mavlink(msg, origin, 0) is None


def test_origin_from_gps_global_origin():
    m = mavlink.MAVLink_gps_global_origin_message(473977459, 85455930, 489056, 768000)
    assert origin_from_mavlink(m) == pytest.approx(ORIGIN)
    assert origin_from_mavlink(mavlink.MAVLink_gps_global_origin_message(0, 0, 0, 0)) is None
    assert origin_from_mavlink(mavlink.MAVLink_gps_global_origin_message(950000000, 0, 0, 0)) is None


# ---------------------------------------------------------------- FcClock

HOST0 = 1_795_750_000_000_000_000      # the host clock when the FC booted (ns)


def test_fc_samples_are_stamped_when_taken_without_the_link_jitter():
    clock = FcClock()
    rng = np.random.default_rng(1)
    stamps = []
    for k in range(500):                                  # 100 Hz IMU, 1-25 ms of transport + scheduling delay
        fc_us = 1_000_000 + k * 10_000
        delay_ns = int(1e6 + rng.exponential(3e6))
        stamps.append(clock.stamp(fc_us, HOST0 + fc_us * 1000 + delay_ns))
    gaps = np.diff(stamps[20:]) / 1e6
    np.testing.assert_allclose(gaps, 10.0, atol=0.2)      # the FC's own 10 ms spacing
    lag_ms = (stamps[-1] - (HOST0 + (1_000_000 + 499 * 10_000) * 1000)) / 1e6
    assert 0.9 < lag_ms < 1.2                             # the least delay seen, a constant


def test_untimed_sample_is_stamped_from_the_newest_fc_timed_one():
    clock = FcClock()
    clock.stamp(1_000_000, HOST0 + 1_000_000_000 + 1_000_000)        # least delay: 1 ms
    imu = clock.stamp(1_010_000, HOST0 + 1_010_000_000 + 21_000_000)  # this one waited 20 ms more
    assert imu == HOST0 + 1_010_000_000 + 1_000_000
    rx = HOST0 + 1_010_000_000 + 25_000_000                           # truth 4 ms behind it
    assert clock.stamp_untimed(rx) == rx - 20_000_000
    later = rx + 50_000_000                                           # none within 20 ms: its receive time
    assert clock.stamp_untimed(later) == later


def test_untimed_before_any_fc_time_is_its_receive_time():
    assert FcClock().stamp_untimed(HOST0) == HOST0


def test_fc_reboot_starts_the_mapping_over():
    clock = FcClock()
    clock.stamp(600_000_000, HOST0 + 600_000_000_000 + 1_000_000)     # 600 s after boot
    rebooted_at = HOST0 + 700_000_000_000                             # FC back at boot time 0
    s = clock.stamp(1_000, rebooted_at + 1_000_000 + 2_000_000)
    assert clock.resets == 1
    assert s == rebooted_at + 1_000_000 + 2_000_000                   # the new offset, not 100 s off


def test_imu_and_truth_stay_on_one_clock_when_the_fc_clock_runs_slow():
    """PX4 SITL's clock is the simulation's: 1.1 % slower than the host's measured under load."""
    clock = FcClock()
    rng = np.random.default_rng(2)
    rate = 0.99                                           # FC seconds per host second
    imu, truth, true_host = [], [], []
    for k in range(3000):                                 # 30 s of 100 Hz IMU, truth 4 ms after each
        fc_us = k * 10_000
        host = HOST0 + int(fc_us * 1000 / rate)           # when the FC took the sample
        jitter = int(1e6 + rng.exponential(3e6))
        imu.append(clock.stamp(fc_us, host + jitter))
        truth.append(clock.stamp_untimed(host + jitter + 4_000_000))
        true_host.append(host)
    imu, truth, true_host = (np.array(v[100:]) for v in (imu, truth, true_host))
    gaps_ms = np.diff(imu) / 1e6
    assert np.median(gaps_ms) == pytest.approx(10.0 / rate, abs=0.01)          # the host's pace
    assert np.all(np.abs(gaps_ms - 10.0 / rate) < 0.6)     # refits step < 0.6 ms (receipt: 1-20 ms jitter)
    assert np.all(np.abs(imu - true_host - 1e6) < 12e6)                       # window x 1 %: ~10 ms late at most
    np.testing.assert_allclose((truth - imu) / 1e6, 4.0, atol=0.05)           # truth on the IMU's clock
