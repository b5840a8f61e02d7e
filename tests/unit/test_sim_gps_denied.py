"""GPS-denied simulated flight controller (services/sim/vehicle/estimator.py): position only from
vision fused with the IMU, PX4's refusals without it and its failsafe when it goes, and the
controller flying on the estimate (so vision error becomes flight error)."""
from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.mavlink import frames
from aeroperception.services.sim.vehicle import MavlinkModule, Setpoint, SimVehicle
from aeroperception.services.sim.vehicle.commander import DENIED, FS_NO_POSITION, TEMPORARILY_REJECTED

M = mavlink
RATE_HZ = 250.0
DT = 1.0 / RATE_HZ
EPOCH_NS = 1_700_000_000 * 10**9


class FakeVio:
    """Vision from the truth in an odom frame that started at `origin` with heading `yaw0` (as a
    VIO initialised there would), `delay_s` late, plus a constant error `bias_m` (odom frame)."""

    def __init__(self, v: SimVehicle, yaw0: float = 0.7, origin=(3.0, -2.0, 0.0), delay_s: float = 0.08,
                 bias_m=(0.0, 0.0, 0.0)):
        self.v, self.delay_ns = v, int(delay_s * 1e9)
        c, s = math.cos(-yaw0), math.sin(-yaw0)
        self.R_odom_enu = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        self.q_odom_enu = frames.quat_from_axis_angle(np.array([0.0, 0.0, -yaw0]))
        self.origin = np.array(origin, float)
        self.bias = np.array(bias_m, float)
        self.queue: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.pos_var_m2 = 0.01 ** 2   # the reported position variance (ODOMETRY covariance)

    def sample(self) -> None:
        s = self.v.state
        p = self.R_odom_enu @ (s.position_enu_m - self.origin) + self.bias
        q = frames.quat_multiply(self.q_odom_enu, s.q_enu_flu)
        vel_body = frames.quat_to_rotmat(s.q_enu_flu).T @ s.velocity_enu_mps
        self.queue.append((self.v.time_ns, p, q, vel_body))

    def deliver(self) -> None:
        while self.queue and self.v.time_ns - self.queue[0][0] >= self.delay_ns:
            t, p, q, vb = self.queue.pop(0)
            self.v.estimator.on_vision(self.v.time_ns, EPOCH_NS + t, p, q, vb, np.full(3, self.pos_var_m2), np.full(3, 0.05**2))


def run(v: SimVehicle, seconds: float, vio: FakeVio | None = None, setpoint: Setpoint | None = None, until=None):
    for i in range(int(round(seconds * RATE_HZ))):
        if vio is not None:
            if i % int(RATE_HZ / 20) == 0:
                vio.sample()
            vio.deliver()
        if setpoint is not None and i % 5 == 0:
            v.commander.on_offboard_setpoint(v.time_s, setpoint)
        v.step(DT)
        if until is not None and until(v):
            return True
    return False


def denied_vehicle(**over) -> SimVehicle:
    v = SimVehicle({"SIM_GPS_DENIED": True, "SIM_WIND_GUST": 0.5, **over}, seed=3)
    v.estimator.epoch_ns = EPOCH_NS
    return v


def test_without_vision_arming_and_offboard_are_refused_with_px4s_reason():
    v = denied_vehicle()
    run(v, 1.0)
    ack = v.commander.arm(v.time_s)
    assert ack.result == DENIED and "Navigation error: No valid position estimate" in ack.reason
    v.commander.on_offboard_setpoint(v.time_s, Setpoint.hold([0, 0, 2], 0.0))
    run(v, 1.5, setpoint=Setpoint.hold([0, 0, 2], 0.0))
    ack = v.commander.set_mode(v.time_s, "OFFBOARD")
    assert ack.result == TEMPORARILY_REJECTED and FS_NO_POSITION in ack.reason
    # the same through MAVLink: SYS_STATUS reports no GPS and no xy position control
    mod = MavlinkModule(v)
    health = mod.streams.sys_status().onboard_control_sensors_health
    assert not health & M.MAV_SYS_STATUS_SENSOR_GPS and not health & M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL


def test_flies_on_vision_aligned_from_a_rotated_odom_frame():
    v = denied_vehicle()
    vio = FakeVio(v)
    run(v, 1.0, vio)
    assert v.estimator.valid(v.time_ns) and v.estimator.counters["ev_alignments"] == 1
    assert v.commander.arm(v.time_s).ok and v.commander.takeoff(v.time_s, 4.0).ok
    assert run(v, 15.0, vio, until=lambda v: v.commander.mode == "HOLD")
    target = np.array([12.0, -6.0, 4.0])
    sp = Setpoint.hold(target, 0.5)
    run(v, 2.0, vio, setpoint=sp)
    assert v.commander.set_mode(v.time_s, "OFFBOARD").ok
    run(v, 20.0, vio, setpoint=sp)
    truth = v.state.position_enu_m
    assert np.linalg.norm(truth - target) < 0.3, truth
    assert np.linalg.norm(v.estimate.position_enu_m - truth) < 0.15
    # LOCAL_POSITION_NED is the estimate
    lp = MavlinkModule(v).streams.local_position_ned()
    assert np.linalg.norm(frames.ned_to_enu([lp.x, lp.y, lp.z]) - v.estimate.position_enu_m) < 0.1


def test_vision_error_becomes_flight_error():
    v = denied_vehicle()
    vio = FakeVio(v, yaw0=0.0, origin=(0, 0, 0))
    run(v, 1.0, vio)
    assert v.commander.arm(v.time_s).ok and v.commander.takeoff(v.time_s, 4.0).ok
    assert run(v, 15.0, vio, until=lambda v: v.commander.mode == "HOLD")
    vio.bias = np.array([1.5, 0.0, 0.0])      # the VIO now believes it is 1.5 m further East
    run(v, 15.0, vio)
    # the FC holds its *estimated* position: the vehicle really moved 1.5 m West
    assert v.state.position_enu_m[0] < -1.2, v.state.position_enu_m


def test_noise_mode_1_fuses_vision_with_the_parameter_not_a_drift_inflated_covariance():
    """A VIO whose covariance includes its accumulated drift (1 m sigma late in a flight) reports a
    slowly varying offset, not per-sample noise: with EKF2_EV_NOISE_MD 1 the FC follows the vision
    at EKF2_EVP_NOISE as it did at the start; with 0 (PX4's default) it would trust its IMU instead."""
    lag = {}
    for mode in (0, 1):
        v = denied_vehicle(EKF2_EV_NOISE_MD=mode)
        vio = FakeVio(v, yaw0=0.0, origin=(0, 0, 0))
        vio.pos_var_m2 = 1.0
        run(v, 1.0, vio)
        vio.bias = np.array([1.0, 0.0, 0.0])   # vision steps 1 m: how far the FC follows in 2 s
        run(v, 2.0, vio)
        lag[mode] = 1.0 - (v.estimate.position_enu_m[0] - v.state.position_enu_m[0])
    assert lag[1] < 0.5 < lag[0], lag


def test_vision_lost_in_flight_px4_failsafe_lands():
    v = denied_vehicle()
    vio = FakeVio(v)
    run(v, 1.0, vio)
    assert v.commander.arm(v.time_s).ok and v.commander.takeoff(v.time_s, 4.0).ok
    assert run(v, 15.0, vio, until=lambda v: v.commander.mode == "HOLD")
    t_lost = v.time_s
    assert run(v, 8.0, until=lambda v: v.commander.failsafe)       # no vision any more
    took = v.time_s - t_lost
    assert abs(took - v.params.EKF2_NOAID_TOUT) < 0.1, took
    assert v.commander.mode == "LAND" and v.commander.failsafe_reason == FS_NO_POSITION
    assert v.commander.set_mode(v.time_s, "RTL").result == TEMPORARILY_REJECTED
    assert run(v, 20.0, until=lambda v: not v.commander.armed)
    assert v.state.position_enu_m[2] < 0.05


def test_vision_back_after_a_gap_is_realigned_not_jumped_to():
    v = denied_vehicle(EKF2_NOAID_TOUT=10.0)
    vio = FakeVio(v)
    run(v, 1.0, vio)
    assert v.commander.arm(v.time_s).ok and v.commander.takeoff(v.time_s, 4.0).ok
    assert run(v, 15.0, vio, until=lambda v: v.commander.mode == "HOLD")
    run(v, 3.0)                                         # blackout: dead-reckoning
    vio.queue.clear()
    vio.origin = v.state.position_enu_m + np.array([5.0, 5.0, 0.0])   # the VIO re-initialised elsewhere
    before = v.estimate.position_enu_m.copy()
    run(v, 0.5, vio)
    assert v.estimator.counters["ev_alignments"] == 2
    assert np.linalg.norm(v.estimate.position_enu_m - before) < 0.3


def test_not_denied_is_the_truth_and_switching_on_live_starts_without_position():
    v = SimVehicle(seed=1)
    run(v, 0.5)
    assert v.estimate.position_enu_m is v.state.position_enu_m and v.estimator.valid(v.time_ns)
    v.params.set("SIM_GPS_DENIED", True)
    run(v, 0.1)
    assert not v.estimator.valid(v.time_ns)
    assert "position" in v.commander.arm(v.time_s).reason


def test_epoch_may_be_a_getter():
    v = denied_vehicle()
    v.estimator.epoch_ns = lambda: EPOCH_NS
    run(v, 1.0, FakeVio(v))
    assert v.estimator.valid(v.time_ns) and v.estimator.counters["vision_late"] == 0


def test_garbage_vision_is_rejected():
    v = denied_vehicle()
    assert not v.estimator.on_vision(v.time_ns, EPOCH_NS, [math.nan, 0, 0], [1, 0, 0, 0])
    assert not v.estimator.on_vision(v.time_ns, EPOCH_NS, [0, 0, 0], [2, 0, 0, 0])
    assert not v.estimator.on_vision(v.time_ns, EPOCH_NS + 10**10, [0, 0, 0], [1, 0, 0, 0])   # from the future
    assert v.estimator.counters["vision_rejected"] == 2 and v.estimator.counters["vision_late"] == 1
    assert not v.estimator.valid(v.time_ns)
