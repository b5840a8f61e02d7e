"""The simulator's follow mode logic (services/sim/follow.py): an external FC's ground truth ->
the truth the renderers take (the scenario's ground under the vehicle on its pad), bad samples
refused, and the measured lag between the truth's stamps and the FC IMU's clock."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import Header, LandedState, Quaternion, Vector3, VehicleState
from aeroperception.services.sim.follow import Follower, ImuLag


def gt(stamp_ns, p=(0.0, 0.0, 0.34), v=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0),
       armed=False, landed=LandedState.ON_GROUND):
    return VehicleState(header=Header(stamp_ns=stamp_ns, frame_id="map"), position_m=Vector3.from_array(p),
                        velocity_mps=Vector3.from_array(v), orientation=Quaternion.from_array(q),
                        angular_velocity_radps=Vector3.from_array(w),
                        armed=armed, landed_state=landed, estimator_name="ground_truth", connected=True)


def flat(_x, _y):
    return 0.0


def test_the_vehicle_on_its_pad_stands_on_the_scenario_ground_from_then_on():
    f = Follower(flat)
    t = f.truth(gt(1, p=(0.3, -0.1, 0.34)))             # PX4 SIH on its pad: 0.34 m above EKF2's origin
    assert f.z_shift_m == pytest.approx(-0.34)
    np.testing.assert_allclose(t.position_enu_m, [0.3, -0.1, 0.0])
    t = f.truth(gt(2, p=(5.0, 2.0, 10.34), armed=True, landed=LandedState.IN_AIR))
    np.testing.assert_allclose(t.position_enu_m, [5.0, 2.0, 10.0])   # x, y: the FC's local frame
    f.truth(gt(3, p=(5.0, 2.0, 0.9)))                    # landed again elsewhere: the shift is kept
    assert f.z_shift_m == pytest.approx(-0.34)


def test_a_vehicle_the_fc_lands_lower_than_its_pad_is_raised_onto_the_ground_and_counted():
    """PX4 SIH measured: 0.12 m on its pad, 0.06 m after a 5 m hop; rendered 6 cm under the ground,
    the cameras (3 cm above the body) saw only the sky colour and VIO was lost on the ground."""
    f = Follower(lambda x, y: 0.1 * x)                   # sloped: the ground's height where it lands
    f.truth(gt(1, p=(0.0, 0.0, 0.12)))
    t = f.truth(gt(2, p=(5.0, 0.0, 0.06), armed=True, landed=LandedState.ON_GROUND))
    np.testing.assert_allclose(t.position_enu_m, [5.0, 0.0, 0.5])
    t = f.truth(gt(3, p=(5.0, 0.0, 0.75), armed=True, landed=LandedState.IN_AIR))   # above it: as the FC says
    np.testing.assert_allclose(t.position_enu_m, [5.0, 0.0, 0.63])
    assert f.below_ground == 1 and f.below_ground_max_m == pytest.approx(0.56)


def test_a_sloped_scenario_puts_its_ground_under_the_pad():
    f = Follower(lambda x, y: 0.1 * x)
    f.truth(gt(1, p=(2.0, 0.0, 0.5)))
    assert f.z_shift_m == pytest.approx(0.2 - 0.5)


def test_started_in_the_air_renders_unshifted_until_landed():
    f = Follower(flat)
    t = f.truth(gt(1, p=(0, 0, 8.0), armed=True, landed=LandedState.IN_AIR))
    assert f.z_shift_m is None and t.position_enu_m[2] == 8.0


def test_truth_carries_stamp_pose_rates_and_acceleration_from_velocity():
    f = Follower(flat)
    half = math.sqrt(0.5)
    f.truth(gt(1_000_000_000, v=(0, 0, 0)))
    t = f.truth(gt(1_010_000_000, v=(0.1, 0, 0), q=(half, 0, 0, half), w=(0, 0, 0.3)))
    assert t.stamp_ns == 1_010_000_000
    np.testing.assert_allclose(t.accel_enu_mps2, [10.0, 0, 0])
    np.testing.assert_allclose(t.q_enu_flu, [half, 0, 0, half])
    np.testing.assert_allclose(t.angular_velocity_flu_radps, [0, 0, 0.3])


@pytest.mark.parametrize("bad", [gt(5, p=(float("nan"), 0, 0)), gt(5, q=(0, 0, 0, 0)), gt(5, w=(0, float("inf"), 0))])
def test_non_finite_samples_are_refused_and_counted(bad):
    f = Follower(flat)
    f.truth(gt(3))
    assert f.truth(bad) is None
    assert (f.rejected, f.out_of_order, f.samples) == (1, 0, 1)


@pytest.mark.parametrize("stamp", [2, 3])                 # older than the last, a duplicate
def test_samples_not_newer_than_the_last_are_skipped_and_counted(stamp):
    f = Follower(flat)
    f.truth(gt(3))
    assert f.truth(gt(stamp)) is None
    assert (f.rejected, f.out_of_order, f.samples) == (0, 1, 1)


def test_a_gap_over_a_second_is_an_outage_counted_with_its_length_and_end():
    f = Follower(flat)
    for k in range(10):                                   # 50 Hz: no outage
        f.truth(gt(int(1e9 + k * 20e6)))
    assert (f.outages, f.last_outage) == (0, None)
    f.truth(gt(int(3.48e9)))                              # fmu restarted: 2.3 s without a sample
    assert f.outages == 1 and f.last_outage == (pytest.approx(2.3), int(3.48e9))
    f.truth(gt(int(4.4e9)))                               # 0.92 s: late, not an outage
    assert f.outages == 1


# ---------------------------------------------------------------- ImuLag


def _wiggle(t_s):
    """Body rates of a vehicle manoeuvring (rad/s)."""
    return np.array([0.4 * np.sin(2 * np.pi * 0.7 * t_s), 0.3 * np.sin(2 * np.pi * 1.1 * t_s + 1), 0.2 * np.sin(2 * np.pi * 0.3 * t_s)])


@pytest.mark.parametrize("lag_ms", [0.0, 4.0, -7.5, 20.0])
def test_lag_of_the_truth_stamps_against_the_fc_imu_is_measured(lag_ms):
    lag = ImuLag()
    rng = np.random.default_rng(3)
    for k in range(400):                                # 4 s of 100 Hz IMU (gyro noise) and 100 Hz truth
        t_imu = k * 0.01
        lag.add_imu(int(t_imu * 1e9), _wiggle(t_imu) + rng.normal(0, 0.01, 3))
        t_true = k * 0.01 + 0.004                       # truth taken 4 ms after each IMU sample...
        lag.add_truth(int((t_true + lag_ms / 1e3) * 1e9), _wiggle(t_true))  # ...stamped lag_ms late
    assert lag.lag_ms() == pytest.approx(lag_ms, abs=1.0)   # linear interpolation of 100 Hz rates: ~0.6 ms bias


def test_lag_reported_is_the_median_of_recent_measurements():
    lag = ImuLag(keep=3)
    lag._measure = iter([-4.0, -15.0, -4.0, None, -3.0]).__next__     # a calm window's outlier, then none
    assert [lag.lag_ms() for _ in range(5)] == [-4.0, -9.5, -4.0, -4.0, -4.0]


def test_lag_needs_rotation_to_see():
    lag = ImuLag()
    for k in range(400):
        lag.add_imu(k * 10_000_000, np.array([0.001, 0, 0]))
        lag.add_truth(k * 10_000_000, np.zeros(3))
    assert lag.lag_ms() is None
    assert ImuLag().lag_ms() is None
