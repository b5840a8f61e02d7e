"""Simulated PX4 multirotor, pure logic (no sockets, no Zenoh): physics, control, commander
rules, and the MAVLink module fed with real encoded/decoded messages."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.mavlink import frames, px4
from aeroperception.services.sim.truth import VehicleTruth
from aeroperception.services.sim.vehicle import (
    PARAMS, MavlinkEndpoint, MavlinkModule, Setpoint, SimVehicle, SimVehicleRunner, make_params,
    setpoint_from_mavlink,
)
from aeroperception.services.sim.vehicle.commander import ACCEPTED, DENIED, TEMPORARILY_REJECTED

M = mavlink
RATE_HZ = 250.0
DT = 1.0 / RATE_HZ


# ---------------------------------------------------------------------------------------------
# helpers

def fly(v: SimVehicle, seconds: float, setpoint: Setpoint | None = None, stream_hz: float = 50.0,
        until=None):
    """Step `seconds` of sim time, streaming `setpoint` as offboard input at `stream_hz` if given.
    Stops early when `until(v)` is true; returns the time it became true (or None)."""
    every = max(1, round(RATE_HZ / stream_hz))
    for i in range(int(round(seconds * RATE_HZ))):
        if setpoint is not None and i % every == 0:
            v.commander.on_offboard_setpoint(v.time_s, setpoint)
        v.step(DT)
        if until is not None and until(v):
            return v.time_s
    return None


def take_off(v: SimVehicle, altitude_m: float = 5.0) -> None:
    c = v.commander
    assert c.arm(v.time_s).ok
    assert c.takeoff(v.time_s, altitude_m).ok
    assert fly(v, 20.0, until=lambda v: v.commander.mode == "HOLD") is not None
    fly(v, 3.0)


def fly_until_disarmed(v: SimVehicle, max_s: float) -> float:
    """Step (no offboard input) until disarmed or max_s; returns the highest altitude seen."""
    max_alt = 0.0
    for _ in range(int(max_s * 5)):
        fly(v, 0.2)
        max_alt = max(max_alt, v.state.position_enu_m[2])
        if not v.commander.armed:
            break
    return max_alt


def start_offboard(v: SimVehicle, target_enu, yaw_rad: float = 0.0) -> Setpoint:
    sp = Setpoint.hold(target_enu, yaw_rad)
    fly(v, 1.2, sp)
    assert v.commander.set_mode(v.time_s, "OFFBOARD").ok
    if not v.commander.armed:
        assert v.commander.arm(v.time_s).ok
    return sp


# ---------------------------------------------------------------------------------------------
# parameters

def test_params_are_declared_once_and_fit_mavlink():
    names = [p.name for p in PARAMS]
    assert len(names) == len(set(names))
    assert all(len(n) <= 16 for n in names), "PARAM_VALUE ids are 16 chars"
    assert all(p.description for p in PARAMS)
    ps = make_params({"SIM_MASS": "2.0"})
    assert ps.SIM_MASS == 2.0


# ---------------------------------------------------------------------------------------------
# physics + position control

def test_rests_on_ground_when_disarmed():
    v = SimVehicle(seed=1)
    v.run_for(2.0)
    assert v.state.position_enu_m[2] == 0.0
    assert v.commander.landed
    assert v.commander.landed_state == M.MAV_LANDED_STATE_ON_GROUND
    np.testing.assert_allclose(v.state.specific_force_flu_mps2(), [0, 0, 9.80665], atol=1e-9)


def test_reaches_position_setpoint_and_holds_within_20cm_in_wind():
    v = SimVehicle({"SIM_WIND_E": 3.0, "SIM_WIND_N": -1.0, "SIM_WIND_GUST": 0.3}, seed=3)
    target = np.array([10.0, 5.0, 5.0])
    sp = start_offboard(v, target)
    reached = fly(v, 20.0, sp, until=lambda v: np.linalg.norm(v.state.position_enu_m - target) < 0.5)
    assert reached is not None, f"did not reach target: {v.state.position_enu_m}"
    fly(v, 10.0, sp)  # settle: the velocity integrator learns the wind
    worst = 0.0
    for _ in range(10 * 5):  # hold 10 s
        fly(v, 0.2, sp)
        worst = max(worst, float(np.linalg.norm(v.state.position_enu_m - target)))
    assert worst < 0.2, f"drifted {worst:.3f} m from the setpoint"
    assert v.commander.mode == "OFFBOARD"


def test_tilt_and_speed_limits_respected():
    v = SimVehicle(seed=0)
    sp = start_offboard(v, [200.0, 0.0, 10.0])
    max_tilt = max_speed = 0.0
    for _ in range(20 * 25):
        fly(v, 0.04, sp)
        R = frames.quat_to_rotmat(v.state.q_enu_flu)
        max_tilt = max(max_tilt, math.degrees(math.acos(R[2, 2])))
        max_speed = max(max_speed, float(np.linalg.norm(v.state.velocity_enu_mps[:2])))
    assert max_tilt <= v.params.MPC_TILTMAX_AIR + 1.0
    assert 5.0 < max_speed <= v.params.MPC_XY_VEL_MAX + 0.5


def test_velocity_and_yaw_rate_setpoints():
    v = SimVehicle(seed=0)
    start_offboard(v, [0.0, 0.0, 5.0])
    fly(v, 6.0, Setpoint.hold([0.0, 0.0, 5.0], 0.0))
    sp = Setpoint(position_enu_m=np.array([math.nan, math.nan, 5.0]), velocity_enu_mps=np.array([0.0, 2.0, math.nan]),
                  yaw_rate_radps=math.radians(20))
    yaw0 = v.state.yaw_rad
    fly(v, 4.0, sp)
    assert v.state.velocity_enu_mps[1] == pytest.approx(2.0, abs=0.2)
    assert v.state.velocity_enu_mps[0] == pytest.approx(0.0, abs=0.2)
    assert v.state.position_enu_m[2] == pytest.approx(5.0, abs=0.2)
    assert frames.wrap_pi(v.state.yaw_rad - yaw0) == pytest.approx(math.radians(80), abs=math.radians(8))


def test_acceleration_feed_forward_is_added_to_the_velocity_controllers_output():
    """Like PX4's PositionControl: the feed-forward joins the velocity PID's acceleration, so a
    hold with 2 m/s^2 east feed-forward accelerates east at first (the loops pull back later)."""
    hold = Setpoint.hold([0.0, 0.0, 5.0], 0.0)

    def east_speed_after(setpoint: Setpoint) -> float:
        v = SimVehicle(seed=0)
        start_offboard(v, [0.0, 0.0, 5.0])
        fly(v, 6.0, hold)
        vx0 = v.state.velocity_enu_mps[0]
        fly(v, 0.4, setpoint)
        return float(v.state.velocity_enu_mps[0] - vx0)

    with_ff = Setpoint(position_enu_m=hold.position_enu_m, velocity_enu_mps=np.zeros(3),
                       accel_enu_mps2=np.array([2.0, 0.0, 0.0]), yaw_rad=0.0)
    gained = east_speed_after(with_ff)
    assert gained > 0.4, f"2 m/s^2 feed-forward for 0.4 s gave {gained:.2f} m/s"
    assert abs(east_speed_after(hold)) < 0.05


def test_level_flight_with_jerk_limited_horizontal_acceleration_stays_level():
    """A level reference that accelerates to 3 m/s^2 at 4 m/s^3 (a planned trajectory's limits),
    east then north: the thrust follows the tilt (|thrust vector| along the commanded attitude, as
    PX4's), so the vehicle barely moves vertically. Measured as `aero eval trajectory` does, by truth:
    vertical jerk 0.27 m/s^3, height within 1.3 cm (thrust not raised with the tilt: 0.69, 7.4 cm)."""
    from aeroperception.tools.eval.trajectory import DIFF_WINDOW_S, _derivative

    ramp = round(0.75 * RATE_HZ)                    # 3 m/s^2 at 4 m/s^3
    pulse = [4.0] * ramp + [0.0] * round(0.5 * RATE_HZ) + [-4.0] * ramp   # up to 3 m/s^2 and back to 0
    leg = pulse + [0.0] * round(0.5 * RATE_HZ) + [-j for j in pulse]      # to 3.75 m/s and back to rest
    jerk = np.zeros((len(leg) * 2 + round(2.0 * RATE_HZ), 3))
    jerk[:len(leg), 0] = leg                        # east, then north
    jerk[len(leg):2 * len(leg), 1] = leg
    acc = np.cumsum(jerk, axis=0) * DT
    vel = np.cumsum(acc, axis=0) * DT
    pos = np.cumsum(vel, axis=0) * DT + [0.0, 0.0, 5.0]

    v = SimVehicle(seed=0)
    start_offboard(v, [0.0, 0.0, 5.0])
    fly(v, 8.0, Setpoint.hold([0.0, 0.0, 5.0], 0.0))
    every = round(RATE_HZ / 50)
    stamps, velocity, height = [], [], []
    for i in range(len(jerk)):
        if i % every == 0:
            v.commander.on_offboard_setpoint(v.time_s, Setpoint(position_enu_m=pos[i], velocity_enu_mps=vel[i],
                                                                 accel_enu_mps2=acc[i], yaw_rad=0.0))
        v.step(DT)
        stamps.append(v.time_s)
        velocity.append(v.state.velocity_enu_mps.copy())
        height.append(v.state.position_enu_m[2])
    t_acc, accel = _derivative(np.array(stamps), np.array(velocity), DIFF_WINDOW_S)
    _, truth_jerk = _derivative(t_acc, accel, DIFF_WINDOW_S)
    assert np.hypot(accel[:, 0], accel[:, 1]).max() > 2.8          # it did accelerate as asked
    assert np.linalg.norm(v.state.position_enu_m[:2] - pos[-1, :2]) < 0.2
    assert np.abs(truth_jerk[:, 2]).max() < 0.5, f"vertical jerk {np.abs(truth_jerk[:, 2]).max():.2f} m/s^3"
    assert np.abs(np.array(height) - 5.0).max() < 0.03

def test_yaw_setpoint_is_followed_at_limited_rate():
    v = SimVehicle(seed=0)
    sp = start_offboard(v, [0.0, 0.0, 3.0], yaw_rad=0.0)
    fly(v, 6.0, sp)
    sp = Setpoint.hold([0.0, 0.0, 3.0], math.pi / 2)
    fly(v, 0.5, sp)
    assert v.state.yaw_rad < math.radians(60 * 0.5) + 0.05  # MC_YAWRATE_MAX 60 deg/s
    fly(v, 3.0, sp)
    assert v.state.yaw_rad == pytest.approx(math.pi / 2, abs=0.02)


# ---------------------------------------------------------------------------------------------
# takeoff, land, auto-disarm

def test_takeoff_to_altitude_then_hold():
    v = SimVehicle(seed=2)
    take_off(v, 5.0)
    c = v.commander
    assert c.mode == "HOLD"
    assert c.landed_state == M.MAV_LANDED_STATE_IN_AIR
    assert v.state.position_enu_m[2] == pytest.approx(5.0, abs=0.2)
    assert np.linalg.norm(v.state.position_enu_m[:2]) < 0.1


def test_takeoff_climb_rate_is_limited():
    v = SimVehicle(seed=2)
    v.commander.arm(0.0)
    v.commander.takeoff(0.0, 10.0)
    vz = []
    for _ in range(50):
        fly(v, 0.1)
        vz.append(v.state.velocity_enu_mps[2])
    assert max(vz) <= v.params.MPC_TKO_SPEED + 0.1


def test_default_takeoff_altitude_and_takeoff_before_arming():
    v = SimVehicle(seed=0)
    assert v.commander.takeoff(v.time_s).ok  # mode only: PX4 does not arm on NAV_TAKEOFF
    fly(v, 1.0)
    assert v.state.position_enu_m[2] == 0.0
    assert v.commander.arm(v.time_s).ok
    fly(v, 10.0, until=lambda v: v.commander.mode == "HOLD")
    assert v.state.position_enu_m[2] == pytest.approx(v.params.MIS_TAKEOFF_ALT, abs=0.25)


def test_land_then_auto_disarm_after_COM_DISARM_LAND():
    v = SimVehicle(seed=4)
    take_off(v, 4.0)
    c = v.commander
    assert c.set_mode(v.time_s, "LAND").ok
    assert c.landed_state == M.MAV_LANDED_STATE_LANDING
    t_landed = fly(v, 30.0, until=lambda v: v.commander.landed)
    assert t_landed is not None
    assert v.state.position_enu_m[2] == 0.0
    assert c.armed, "must not disarm at the moment of landing"
    t_disarmed = fly(v, 5.0, until=lambda v: not v.commander.armed)
    assert t_disarmed is not None
    assert t_disarmed - t_landed == pytest.approx(v.params.COM_DISARM_LAND, abs=0.05)
    assert c.counters["auto_disarms"] == 1


def test_land_descent_rate_follows_PX4_profile():
    v = SimVehicle(seed=4)
    take_off(v, 15.0)
    v.commander.set_mode(v.time_s, "LAND")
    fly(v, 3.0)
    assert -v.state.velocity_enu_mps[2] == pytest.approx(v.params.MPC_Z_VEL_MAX_DN, abs=0.15)  # above ALT1
    fly(v, 60.0, until=lambda v: v.state.position_enu_m[2] < 3.0)
    assert -v.state.velocity_enu_mps[2] == pytest.approx(v.params.MPC_LAND_SPEED, abs=0.1)  # below ALT2


def test_disarmed_after_a_landing_it_is_back_in_the_last_mode_it_can_arm_in_as_px4():
    """PX4's user mode intention: LAND and RTL prevent arming, so on disarm PX4 switches to the last
    mode asked for that does not (seen on PX4 SITL: OFFBOARD again in the disarm's heartbeat)."""
    v = SimVehicle(seed=4)
    take_off(v, 4.0)
    c = v.commander
    assert c.set_mode(v.time_s, "LAND").ok
    assert fly(v, 40.0, until=lambda v: not v.commander.armed) is not None
    assert c.mode == "HOLD"                    # take_off's last armable mode
    sp = start_offboard(v, [0.0, 0.0, 3.0])
    fly(v, 5.0, sp)
    assert c.set_mode(v.time_s, "LAND").ok
    assert fly(v, 40.0, sp, until=lambda v: not v.commander.armed) is not None
    assert c.mode == "OFFBOARD" and not c.armed and v.state.position_enu_m[2] == 0.0


def test_preflight_auto_disarm_when_no_takeoff():
    v = SimVehicle(seed=0)
    assert v.commander.arm(0.0).ok
    t = fly(v, 15.0, until=lambda v: not v.commander.armed)
    assert t == pytest.approx(v.params.COM_DISARM_PRFLT, abs=0.05)


def test_rtl_climbs_returns_and_lands_at_home():
    v = SimVehicle({"RTL_RETURN_ALT": 12.0}, seed=5)
    sp = start_offboard(v, [15.0, -10.0, 6.0])
    fly(v, 15.0, sp)
    assert v.commander.set_mode(v.time_s, "RTL").ok
    max_alt = fly_until_disarmed(v, 120.0)
    assert not v.commander.armed
    assert max_alt == pytest.approx(12.0, abs=0.5)
    assert np.linalg.norm(v.state.position_enu_m[:2]) < 1.0
    assert v.state.position_enu_m[2] == 0.0


# ---------------------------------------------------------------------------------------------
# arming rules

def test_arm_refused_without_position():
    v = SimVehicle({"SIM_POS_VALID": False}, seed=0)
    ack = v.commander.arm(0.0)
    assert ack.result == DENIED and "position" in ack.reason
    assert v.commander.arm(0.0, force=True).ok


def test_disarm_in_air_refused_unless_forced_then_falls():
    v = SimVehicle(seed=0)
    take_off(v, 5.0)
    c = v.commander
    assert c.disarm(v.time_s).result == DENIED
    assert c.armed
    assert c.disarm(v.time_s, force=True).ok
    t = fly(v, 5.0, until=lambda v: v.state.position_enu_m[2] == 0.0)
    assert t is not None
    fly(v, 0.1)
    assert c.landed and c.arm(v.time_s).ok  # on the ground again: arming possible


def test_arm_refused_in_air_while_falling():
    v = SimVehicle(seed=0)
    take_off(v, 20.0)
    v.commander.disarm(v.time_s, force=True)
    fly(v, 0.3)
    ack = v.commander.arm(v.time_s)
    assert ack.result == DENIED and "landed" in ack.reason


def test_flight_termination_falls_latches_and_reboot_clears():
    v = SimVehicle(seed=0)
    take_off(v, 5.0)
    c = v.commander
    assert c.terminate(v.time_s).ok
    assert not c.armed and c.mode == "TERMINATION"
    fly(v, 3.0)
    assert v.state.position_enu_m[2] == 0.0
    assert c.arm(v.time_s, force=True).result == DENIED
    assert c.set_mode(v.time_s, "HOLD").result == DENIED
    v.reboot()
    assert not v.commander.terminated and v.commander.arm(v.time_s).ok


# ---------------------------------------------------------------------------------------------
# offboard rules

def test_offboard_refused_without_stream():
    v = SimVehicle(seed=0)
    c = v.commander
    ack = c.set_mode(v.time_s, "OFFBOARD")
    assert ack.result == TEMPORARILY_REJECTED
    assert c.mode == "HOLD"
    sp = Setpoint.hold([0.0, 0.0, 2.0], 0.0)
    fly(v, 0.6, sp)                                   # streaming, but not for 1 s yet
    assert c.set_mode(v.time_s, "OFFBOARD").result == TEMPORARILY_REJECTED
    fly(v, 3.0, sp, stream_hz=1.5)                    # long enough, but too slow (< 2 Hz)
    assert c.set_mode(v.time_s, "OFFBOARD").result == TEMPORARILY_REJECTED
    fly(v, 1.1, sp, stream_hz=10.0)
    assert c.set_mode(v.time_s, "OFFBOARD").ok


def test_arming_in_offboard_requires_the_stream():
    v = SimVehicle(seed=0)
    sp = Setpoint.hold([0.0, 0.0, 2.0], 0.0)
    fly(v, 1.2, sp)
    assert v.commander.set_mode(v.time_s, "OFFBOARD").ok
    fly(v, 2.0)  # stream stops while disarmed
    ack = v.commander.arm(v.time_s)
    assert ack.result == DENIED and "offboard" in ack.reason


def test_offboard_loss_fails_over_to_hold_then_land():
    v = SimVehicle({"COM_OBL_ACT": 1, "COM_OBL_HOLD_T": 3.0, "SIM_OF_RESUME": False}, seed=0)
    sp = start_offboard(v, [3.0, 0.0, 5.0])
    fly(v, 10.0, sp)
    c = v.commander
    t_lost = v.time_s
    fly(v, 0.95)
    assert c.mode == "OFFBOARD" and not c.failsafe
    t_hold = fly(v, 0.5, until=lambda v: v.commander.mode == "HOLD")
    assert t_hold is not None and t_hold - t_lost == pytest.approx(v.params.COM_OF_LOSS_T, abs=0.02)
    assert c.failsafe and "offboard" in c.failsafe_reason
    pos_at_loss = v.state.position_enu_m.copy()
    t_land = fly(v, 5.0, until=lambda v: v.commander.mode == "LAND")
    assert t_land - t_hold == pytest.approx(3.0, abs=0.02)
    assert np.linalg.norm(v.state.position_enu_m - pos_at_loss) < 0.3  # held position meanwhile
    # with SIM_OF_RESUME off, setpoints coming back do not return to OFFBOARD by themselves
    fly(v, 2.0, sp)
    assert c.mode == "LAND"


def test_offboard_loss_default_is_rtl_like_px4_sitl_and_setpoints_back_resume_offboard():
    """PX4 SITL defaults: RTL COM_OF_LOSS_T after the last setpoint; the failsafe clears when the
    stream comes back and the vehicle is in OFFBOARD again (the PX4 facts in ARCHITECTURE §7)."""
    v = SimVehicle(seed=0)
    assert v.params.COM_OBL_ACT == 2 and v.params.SIM_OF_RESUME
    sp = start_offboard(v, [3.0, 0.0, 5.0])
    fly(v, 10.0, sp)
    c = v.commander
    t_lost = v.time_s
    t_rtl = fly(v, 1.5, until=lambda v: v.commander.mode == "RTL")
    assert t_rtl is not None and t_rtl - t_lost == pytest.approx(v.params.COM_OF_LOSS_T, abs=0.02)
    assert c.failsafe and "offboard" in c.failsafe_reason
    fly(v, 2.0)
    assert v.state.position_enu_m[2] > 5.5  # climbing to RTL_RETURN_ALT
    t_back = fly(v, 1.0, sp, until=lambda v: v.commander.mode == "OFFBOARD")
    assert t_back is not None and t_back - v.time_s < 0.05 and not c.failsafe
    assert c.counters["offboard_resumed"] == 1
    fly(v, 10.0, sp)
    np.testing.assert_allclose(v.state.position_enu_m, [3.0, 0.0, 5.0], atol=0.3)  # following again


def test_offboard_loss_rtl_lands_at_home_and_disarms_without_setpoints():
    v = SimVehicle({"RTL_RETURN_ALT": 8.0}, seed=1)
    sp = start_offboard(v, [6.0, 4.0, 5.0])
    fly(v, 10.0, sp)
    max_alt = fly_until_disarmed(v, 60.0)
    assert not v.commander.armed and max_alt == pytest.approx(8.0, abs=0.5)
    assert np.linalg.norm(v.state.position_enu_m[:2]) < 1.0 and v.state.position_enu_m[2] == 0.0
    fly(v, 1.0, sp)
    # landed: the failsafe is over, nothing resumes; disarmed, it is back in the last mode asked for
    # that it can arm in (OFFBOARD), as PX4 reports after its RTL failsafe lands
    assert not v.commander.armed and v.state.position_enu_m[2] == 0.0
    assert v.commander.mode == "OFFBOARD" and not v.commander.failsafe


def test_user_mode_change_takes_over_from_failsafe():
    v = SimVehicle(seed=0)
    sp = start_offboard(v, [0.0, 0.0, 5.0])
    fly(v, 8.0, sp)
    fly(v, 1.5)
    assert v.commander.failsafe
    assert v.commander.set_mode(v.time_s, "POSCTL").ok
    assert not v.commander.failsafe
    fly(v, 10.0)
    assert v.commander.mode == "POSCTL"


def test_modes_without_rc_or_mission_are_rejected():
    v = SimVehicle(seed=0)
    for mode in ("MISSION", "MANUAL", "ALTCTL", "STABILIZED", "ACRO"):
        assert v.commander.set_mode(0.0, mode).result == TEMPORARILY_REJECTED


def test_low_battery_action_rtl_then_land():
    v = SimVehicle({"COM_LOW_BAT_ACT": 3, "SIM_BAT_DRAIN": 100.0, "RTL_RETURN_ALT": 8.0}, seed=0)
    sp = start_offboard(v, [5.0, 0.0, 5.0])
    fly(v, 60.0, sp, until=lambda v: v.commander.mode != "OFFBOARD")
    assert v.commander.mode == "RTL" and v.commander.failsafe_reason == "battery critical"


# ---------------------------------------------------------------------------------------------
# determinism, truth

def _trajectory(seed: int) -> np.ndarray:
    v = SimVehicle({"SIM_WIND_GUST": 1.0}, seed=seed)
    sp = start_offboard(v, [4.0, 4.0, 4.0])
    out = []
    for _ in range(40):
        fly(v, 0.1, sp)
        out.append(np.concatenate([v.state.position_enu_m, v.state.q_enu_flu]))
    return np.array(out)


def test_deterministic_for_a_seed():
    a, b, c = _trajectory(7), _trajectory(7), _trajectory(8)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_truth_is_enu_flu_and_stamped():
    v = SimVehicle(seed=0)
    take_off(v, 3.0)
    t = v.truth()
    assert isinstance(t, VehicleTruth)
    assert t.stamp_ns == v.time_ns
    assert t.position_enu_m[2] == pytest.approx(3.0, abs=0.2)
    assert t.q_enu_flu.shape == (4,) and t.q_enu_flu[0] > 0.99  # level, facing East (yaw 0)
    t.position_enu_m[0] = 99.0  # a copy, not a view of the state
    assert v.state.position_enu_m[0] != 99.0


def test_runner_calls_on_truth_and_survives_a_failing_callback():
    seen = []
    r = SimVehicleRunner(SimVehicle(seed=0), on_truth=seen.append, truth_rate_hz=100.0)
    r.run_for(1.0)
    assert abs(len(seen) - 100) <= 1
    gaps_ms = np.diff([t.stamp_ns for t in seen]) / 1e6
    assert 8.0 <= gaps_ms.min() and gaps_ms.max() <= 12.0 and gaps_ms.mean() == pytest.approx(10.0, abs=0.1)
    assert seen[-1].stamp_ns == r.now_ns() == 1_000_000_000

    def boom(_):
        raise RuntimeError("publisher down")
    r.on_truth = boom
    r.run_for(0.1)
    assert r.callback_errors > 0 and r.now_ns() == 1_100_000_000


def test_runner_paces_with_a_fake_clock():
    wall = [0.0]

    def sleep(s):
        wall[0] += max(s, 1e-4)

    r = SimVehicleRunner(SimVehicle(seed=0), speed=4.0, wall_clock=lambda: wall[0], sleep=sleep)

    class StopAfter:
        def is_set(self):
            return wall[0] >= 1.0
    r.run(StopAfter())
    assert r.vehicle.time_s == pytest.approx(4.0, abs=0.02)


# ---------------------------------------------------------------------------------------------
# MAVLink module (real encode -> decode, no socket)

GCS = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)


def wire(msg):
    """What the vehicle would receive: packed by a GCS, parsed back."""
    parser = mavlink.MAVLink(None)
    return parser.parse_buffer(msg.pack(GCS))[0]


def cmd(command, *params, target=(1, 1)):
    p = list(params) + [0.0] * (7 - len(params))
    return wire(GCS.command_long_encode(target[0], target[1], command, 0, *p))


def acks(replies):
    return [(r.command, r.result) for r in replies if r.get_type() == "COMMAND_ACK"]


def by_type(replies, mtype):
    return [r for r in replies if r.get_type() == mtype]


@pytest.fixture
def mod():
    return MavlinkModule(SimVehicle(seed=0))


def test_every_command_is_acked(mod):
    unknown = mod.handle(cmd(M.MAV_CMD_DO_SET_SERVO, 1, 1500))
    assert acks(unknown) == [(M.MAV_CMD_DO_SET_SERVO, M.MAV_RESULT_UNSUPPORTED)]
    replies = mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1))
    assert acks(replies) == [(M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_RESULT_ACCEPTED)]
    ack = by_type(replies, "COMMAND_ACK")[0]
    assert (ack.target_system, ack.target_component) == (255, 190)
    assert mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(7, 1))) == []  # not for us


def test_refusals_come_with_a_statustext(mod):
    replies = mod.handle(cmd(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0))
    assert acks(replies) == [(M.MAV_CMD_DO_SET_MODE, M.MAV_RESULT_TEMPORARILY_REJECTED)]
    assert "offboard" in by_type(replies, "STATUSTEXT")[0].text


def test_do_set_mode_uses_px4_main_and_sub(mod):
    main, sub = px4.PX4_MODES["LAND"]
    assert acks(mod.handle(cmd(M.MAV_CMD_DO_SET_MODE, 1, main, sub)))[0][1] == ACCEPTED
    assert mod.commander.mode == "LAND"
    hb = mod.streams.heartbeat()
    assert px4.decode(hb.custom_mode) == "LAND" and hb.custom_mode == 0x06040000
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert acks(mod.handle(cmd(M.MAV_CMD_DO_SET_MODE, 1, 42, 0)))[0][1] == DENIED
    # legacy SET_MODE message
    replies = mod.handle(wire(GCS.set_mode_encode(1, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, px4.encode("HOLD"))))
    assert acks(replies) == [(M.MAV_CMD_DO_SET_MODE, ACCEPTED)] and mod.commander.mode == "HOLD"


def test_heartbeat_armed_flag(mod):
    assert not mod.streams.heartbeat().base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1))
    hb = mod.streams.heartbeat()
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.system_status == M.MAV_STATE_ACTIVE


def test_nav_takeoff_param7_is_amsl(mod):
    home = mod.vehicle.params.SIM_HOME_ALT
    takeoff = cmd(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, home + 7.0)
    assert acks(mod.handle(takeoff))[0][1] == ACCEPTED
    mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1))
    mod.vehicle.run_for(12.0)
    assert mod.vehicle.state.position_enu_m[2] == pytest.approx(7.0, abs=0.25)
    assert acks(mod.handle(cmd(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0)))[0][1] == DENIED  # below home


def test_force_arm_and_force_disarm_magic(mod):
    mod.vehicle.params.set("SIM_POS_VALID", False)
    assert acks(mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)))[0][1] == DENIED
    assert acks(mod.handle(cmd(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196)))[0][1] == ACCEPTED


IGNORE_POS = M.POSITION_TARGET_TYPEMASK_X_IGNORE | M.POSITION_TARGET_TYPEMASK_Y_IGNORE \
    | M.POSITION_TARGET_TYPEMASK_Z_IGNORE
IGNORE_VEL = M.POSITION_TARGET_TYPEMASK_VX_IGNORE | M.POSITION_TARGET_TYPEMASK_VY_IGNORE \
    | M.POSITION_TARGET_TYPEMASK_VZ_IGNORE
IGNORE_ACC = M.POSITION_TARGET_TYPEMASK_AX_IGNORE | M.POSITION_TARGET_TYPEMASK_AY_IGNORE \
    | M.POSITION_TARGET_TYPEMASK_AZ_IGNORE
IGNORE_YAW = M.POSITION_TARGET_TYPEMASK_YAW_IGNORE
IGNORE_YAW_RATE = M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
POSITION_AND_YAW = IGNORE_VEL | IGNORE_ACC | IGNORE_YAW_RATE


def test_type_mask_bits_are_PX4s():
    assert (IGNORE_POS, IGNORE_VEL, IGNORE_ACC, IGNORE_YAW, IGNORE_YAW_RATE) == (7, 56, 448, 1024, 2048)


def test_set_position_target_type_mask_and_frames():
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, POSITION_AND_YAW,
                                                      1.0, 2.0, -3.0, 9, 9, 9, 9, 9, 9, 0.0, 9))
    sp = setpoint_from_mavlink(m)
    np.testing.assert_allclose(sp.position_enu_m, [2.0, 1.0, 3.0])
    assert np.isnan(sp.velocity_enu_mps).all() and np.isnan(sp.accel_enu_mps2).all()
    assert sp.yaw_rad == pytest.approx(math.pi / 2) and math.isnan(sp.yaw_rate_radps)
    # velocity only, with yaw rate: North 1 m/s, climbing 0.5 m/s, yawing clockwise
    vel_mask = IGNORE_POS | IGNORE_ACC | IGNORE_YAW
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, vel_mask,
                                                      0, 0, 0, 1.0, 0.0, -0.5, 0, 0, 0, 0.0, 0.3))
    sp = setpoint_from_mavlink(m)
    assert np.isnan(sp.position_enu_m).all()
    np.testing.assert_allclose(sp.velocity_enu_mps, [0.0, 1.0, 0.5])
    assert math.isnan(sp.yaw_rad) and sp.yaw_rate_radps == pytest.approx(-0.3)
    # a z-only position (x/y ignored): NaN maps to the right ENU axes
    z_only = M.POSITION_TARGET_TYPEMASK_X_IGNORE | M.POSITION_TARGET_TYPEMASK_Y_IGNORE | IGNORE_VEL | IGNORE_ACC \
        | IGNORE_YAW_RATE
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, z_only,
                                                      7, 7, -4.0, 0, 0, 0, 0, 0, 0, 0.0, 0))
    sp = setpoint_from_mavlink(m)
    assert np.isnan(sp.position_enu_m[:2]).all() and sp.position_enu_m[2] == 4.0
    # acceleration feed-forward NED -> ENU; with FORCE_SET the same numbers are a force: ignored
    acc_mask = IGNORE_POS | IGNORE_YAW | IGNORE_YAW_RATE
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, acc_mask,
                                                      0, 0, 0, 0, 0, 0, 1.0, 2.0, -3.0, 0.0, 0))
    np.testing.assert_allclose(setpoint_from_mavlink(m).accel_enu_mps2, [2.0, 1.0, 3.0])
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED,
                                                      acc_mask | M.POSITION_TARGET_TYPEMASK_FORCE_SET,
                                                      0, 0, 0, 0, 0, 0, 1.0, 2.0, -3.0, 0.0, 0))
    assert np.isnan(setpoint_from_mavlink(m).accel_enu_mps2).all()
    m = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_BODY_NED, 0, *[0] * 11))
    assert setpoint_from_mavlink(m) is None


def test_setpoint_messages_feed_the_offboard_stream(mod):
    msg = wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, POSITION_AND_YAW,
                                                        0, 0, -2.0, 0, 0, 0, 0, 0, 0, 0, 0))
    for _ in range(60):
        mod.handle(msg)
        mod.vehicle.run_for(0.02)
    assert mod.counters["setpoints"] == 60
    assert acks(mod.handle(cmd(M.MAV_CMD_DO_SET_MODE, 1, 6, 0)))[0][1] == ACCEPTED


def test_timesync_answered_with_sim_time(mod):
    mod.vehicle.run_for(0.5)
    (reply,) = mod.handle(wire(GCS.timesync_encode(0, 123456789)))
    assert reply.tc1 == mod.vehicle.time_ns == 500_000_000 and reply.ts1 == 123456789
    assert mod.handle(wire(GCS.timesync_encode(5, 1))) == []  # a response, not a request


def test_request_message_interval_and_capabilities(mod):
    replies = mod.handle(cmd(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
    assert acks(replies)[0][1] == ACCEPTED
    (ver,) = by_type(replies, "AUTOPILOT_VERSION")
    for cap in (M.MAV_PROTOCOL_CAPABILITY_MISSION_INT, M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
                M.MAV_PROTOCOL_CAPABILITY_MAVLINK2, M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED):
        assert ver.capabilities & cap
    assert by_type(mod.handle(cmd(M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1)), "AUTOPILOT_VERSION")
    assert by_type(mod.handle(cmd(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)), "HOME_POSITION")
    assert acks(mod.handle(cmd(M.MAV_CMD_REQUEST_MESSAGE, 12345)))[0][1] == DENIED

    def count(mtype, seconds=2.0):
        n = 0
        for _ in range(int(seconds * RATE_HZ)):
            mod.vehicle.step(DT)
            n += len(by_type(mod.tick(), mtype))
        return n
    # PX4's onboard defaults: local position 30 Hz, IMU 50 Hz
    assert count("LOCAL_POSITION_NED") == pytest.approx(60, abs=2)
    assert count("HIGHRES_IMU") == pytest.approx(100, abs=2)
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100_000))
    assert count("LOCAL_POSITION_NED") == pytest.approx(20, abs=1)
    replies = mod.handle(cmd(M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED))
    (iv,) = by_type(replies, "MESSAGE_INTERVAL")
    assert iv.interval_us == 100_000
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1))
    assert count("LOCAL_POSITION_NED") == 0
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0))
    assert count("LOCAL_POSITION_NED") == pytest.approx(60, abs=2)


def run_module(mod, seconds):
    out = []
    for _ in range(int(round(seconds * RATE_HZ))):
        mod.vehicle.step(DT)
        out += mod.tick()
    return out


def test_a_faster_stream_rate_applies_from_the_next_step(mod):
    """The streams skip their scan until the earliest is due; a new interval must not wait for
    the old schedule (local position at 30 Hz, then 250 Hz: next step, and every step on)."""
    ticks = []
    while not by_type(ticks, "LOCAL_POSITION_NED"):
        mod.vehicle.step(DT)
        ticks = mod.tick()
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1e6 / RATE_HZ))
    assert [len(by_type(run_module(mod, DT), "LOCAL_POSITION_NED")) for _ in range(5)] == [1] * 5
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1))
    assert by_type(run_module(mod, 0.5), "LOCAL_POSITION_NED") == []


def test_reboot_like_px4_silent_then_boot_time_from_zero_and_default_rates(mod):
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000))  # 50 Hz
    out = run_module(mod, 5.0)
    assert len(by_type(out, "LOCAL_POSITION_NED")[-50:]) == 50
    before_ms = by_type(out, "LOCAL_POSITION_NED")[-1].time_boot_ms
    assert before_ms == pytest.approx(5000, abs=30)
    mod.vehicle.commander.arm(mod.now_s)
    assert acks(mod.handle(cmd(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1))) == [
        (M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, DENIED)]  # armed: refused, as PX4
    mod.vehicle.commander.disarm(mod.now_s)
    assert acks(mod.handle(cmd(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1))) == [
        (M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, ACCEPTED)]  # the ACK goes out before it goes silent
    assert mod.vehicle.reboots == 1
    silent = run_module(mod, mod.vehicle.params.SIM_REBOOT_T - 0.1)
    assert silent == [] and mod.handle(cmd(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)) == []
    back = run_module(mod, 2.1)
    lp = by_type(back, "LOCAL_POSITION_NED")
    assert len(lp) == pytest.approx(2.0 * 30, abs=3)           # PX4's default rate again, until asked
    assert lp[0].time_boot_ms < before_ms and lp[0].time_boot_ms == pytest.approx(2000, abs=120)
    assert by_type(back, "HEARTBEAT")
    mod.handle(cmd(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000))
    assert len(by_type(run_module(mod, 1.0), "LOCAL_POSITION_NED")) == pytest.approx(50, abs=2)


def test_setpoint_truth_counts_non_finite_used_fields_and_the_fastest_velocity(mod):
    ignore_pos = sum(int(b) for b in (M.POSITION_TARGET_TYPEMASK_X_IGNORE, M.POSITION_TARGET_TYPEMASK_Y_IGNORE,
                                      M.POSITION_TARGET_TYPEMASK_Z_IGNORE))
    nan = float("nan")

    def sp(mask, pos, vel, acc=(0, 0, 0)):
        return wire(GCS.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask, *pos, *vel,
                                                              *acc, 0, 0))
    mod.handle(sp(ignore_pos, (nan, nan, nan), (3.0, 4.0, 0.0)))      # NaN only where ignored: fine
    assert mod.diagnostics()["setpoints_nonfinite"] == 0
    assert mod.diagnostics()["setpoint_max_speed_mps"] == pytest.approx(5.0)
    mod.handle(sp(ignore_pos, (0, 0, 0), (nan, 1.0, 0.0)))
    mod.handle(sp(0, (float("inf"), 0, 0), (0, 0, 0)))
    mod.handle(sp(ignore_pos, (0, 0, 0), (1000.0, 0.0, 0.0)))
    d = mod.diagnostics()
    assert d["setpoints_nonfinite"] == 2 and d["setpoint_max_speed_mps"] == pytest.approx(1000.0)
    mod.handle(sp(ignore_pos | IGNORE_ACC, (0, 0, 0), (0, 0, 0), (nan, 0, 0)))   # ignored acceleration: fine
    mod.handle(sp(ignore_pos, (0, 0, 0), (0, 0, 0), (0, nan, 0)))                # used: counted
    assert mod.diagnostics()["setpoints_nonfinite"] == 3


def test_telemetry_is_ned(mod):
    v = mod.vehicle
    take_off(v, 4.0)
    lp = mod.streams.local_position_ned()
    assert lp.z == pytest.approx(-4.0, abs=0.2)
    att = mod.streams.attitude()
    assert att.yaw == pytest.approx(math.pi / 2, abs=0.05)  # ENU yaw 0 = facing East = heading 90 deg
    aq = mod.streams.attitude_quaternion()
    q_enu = frames.q_ned_frd_to_enu_flu([aq.q1, aq.q2, aq.q3, aq.q4])
    np.testing.assert_allclose(q_enu, frames.quat_normalize(v.state.q_enu_flu), atol=1e-6)
    imu = mod.streams.highres_imu()
    assert imu.zacc == pytest.approx(-9.81, abs=0.3)  # FRD: specific force points up = -z
    gp = mod.streams.global_position_int()
    assert gp.relative_alt == pytest.approx(4000, abs=200)
    assert gp.alt == pytest.approx(v.params.SIM_HOME_ALT * 1000 + 4000, abs=200)
    assert gp.hdg == pytest.approx(9000, abs=300)
    assert mod.streams.extended_sys_state().landed_state == M.MAV_LANDED_STATE_IN_AIR
    bs = mod.streams.battery_status()
    assert 0 < bs.battery_remaining <= 100 and bs.voltages[0] > 12000 and bs.current_battery > 0


def test_vision_messages_are_counted(mod):
    q = [1.0, 0.0, 0.0, 0.0]
    nan21 = [math.nan] + [0.0] * 20
    odom = GCS.odometry_encode(0, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, 0.1, 0.0, 0.0, q,
                               0, 0, 0, 0, 0, 0, nan21, nan21, 0, M.MAV_ESTIMATOR_TYPE_VISION)
    mod.handle(wire(odom))
    mod.handle(wire(GCS.vision_position_estimate_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
    d = mod.diagnostics()
    assert d["vision_odometry"] == 1 and d["vision_position"] == 1
    assert d["vision_error_m"] == pytest.approx(0.0, abs=1e-9)


def test_param_protocol(mod):
    n = len(PARAMS)
    values = mod.handle(wire(GCS.param_request_list_encode(1, 1)))
    assert len(values) == n and {v.param_count for v in values} == {n}
    (v,) = mod.handle(wire(GCS.param_request_read_encode(1, 1, b"SIM_MASS", -1)))
    assert v.param_id == "SIM_MASS" and v.param_value == pytest.approx(1.5)
    (v,) = mod.handle(wire(GCS.param_set_encode(1, 1, b"COM_OF_LOSS_T", 2.5, M.MAV_PARAM_TYPE_REAL32)))
    assert v.param_value == pytest.approx(2.5) and mod.vehicle.params.COM_OF_LOSS_T == 2.5
    # int parameters travel bytewise, like PX4's
    bytewise_3 = np.frombuffer(np.int32(3).tobytes(), np.float32)[0]
    (v,) = mod.handle(wire(GCS.param_set_encode(1, 1, b"COM_LOW_BAT_ACT", bytewise_3, M.MAV_PARAM_TYPE_INT32)))
    assert mod.vehicle.params.COM_LOW_BAT_ACT == 3 and v.param_type == M.MAV_PARAM_TYPE_INT32
    # an invalid value is refused: current value echoed + a reason
    replies = mod.handle(wire(GCS.param_set_encode(1, 1, b"SIM_MASS", -4.0, M.MAV_PARAM_TYPE_REAL32)))
    assert by_type(replies, "PARAM_VALUE")[0].param_value == pytest.approx(1.5)
    assert by_type(replies, "STATUSTEXT")


def test_mission_and_ftp_are_answered_not_ignored(mod):
    (count,) = mod.handle(wire(GCS.mission_request_list_encode(1, 1, 0)))
    assert count.get_type() == "MISSION_COUNT" and count.count == 0
    (nak,) = mod.handle(wire(GCS.file_transfer_protocol_encode(0, 1, 1, [7, 0, 0, 4] + [0] * 247)))
    payload = bytes(nak.payload)
    assert payload[0] == 8 and payload[3] == 129 and payload[5] == 4  # seq+1, NAK, for OpenFileRO


def test_malformed_but_valid_crc_message_is_dropped(mod):
    bad = wire(GCS.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, math.nan, math.nan, 0, 0, 0, 0, 0))
    assert acks(mod.handle(bad)) == [(M.MAV_CMD_DO_SET_MODE, DENIED)]
    assert mod.handle(wire(GCS.param_request_read_encode(1, 1, b"NOPE", -1))) == []


def test_endpoint_counts_and_drops_garbage():
    rx = MavlinkEndpoint(target=("127.0.0.1", 9), bind=("127.0.0.1", 0))
    import socket
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        good = GCS.heartbeat_encode(6, 8, 0, 0, 0).pack(GCS)
        corrupt = bytearray(good)
        corrupt[-1] ^= 0xFF  # bad CRC
        rng = np.random.default_rng(0)
        for data in (bytes(rng.integers(0, 256, 300, dtype=np.uint8)), bytes(corrupt), good[:7],
                     b"\xfd\xff" + b"\x00" * 5, good + good, b""):
            tx.sendto(data, rx.local_address)
        import time
        msgs = []
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and rx.counters["rx_datagrams"] < 6:
            msgs += rx.receive()
            time.sleep(0.01)
        assert [m.get_type() for m in msgs] == ["HEARTBEAT", "HEARTBEAT"]
        assert rx.counters["rx_bad"] >= 4
    finally:
        tx.close()
        rx.close()


# ---------------------------------------------------------------------------------------------
# terrain: the physics ground is the scenario's ground (slope_forest's 10 deg slope)

def _slope():
    from aeroperception.services.sim.world.scenario import load_scenario

    scn = load_scenario("slope_forest")
    assert scn.ground.slope_deg == 10.0
    return scn.ground_height_m


def test_lands_rests_and_takes_off_on_the_slope_where_the_scenario_ground_is():
    terrain = _slope()
    v = SimVehicle({"COM_DISARM_LAND": 2.0, "MIS_TAKEOFF_ALT": 4.0}, seed=6, terrain=terrain)
    uphill = np.array([25.0, 0.0])
    ground = terrain(*uphill)
    assert ground == pytest.approx(25.0 * math.tan(math.radians(10.0)))      # 4.4 m above home
    # Fly up the slope at 2 m above home: the slope rises above that on the way, so the
    # vehicle meets it and is held there (flat physics flew through it); the land detector
    # fires on the slope and it auto-disarms, as PX4 does.
    sp = start_offboard(v, [uphill[0], uphill[1], 2.0])
    fly(v, 25.0, sp, until=lambda v: not v.commander.armed)
    s = v.state
    assert not v.commander.armed and v.commander.landed
    assert 2.0 < s.position_enu_m[0] < uphill[0] and s.resting
    assert s.position_enu_m[2] == pytest.approx(terrain(*s.position_enu_m[:2]), abs=1e-9)
    assert s.ground_z_m == pytest.approx(terrain(*s.position_enu_m[:2]))
    # Resting on the slope: still, level, an accelerometer reading 1 g up.
    fly(v, 2.0)
    np.testing.assert_allclose(v.state.velocity_enu_mps, 0.0)
    np.testing.assert_allclose(v.state.specific_force_flu_mps2(), [0, 0, 9.80665], atol=1e-9)
    # Take-off from there climbs MIS_TAKEOFF_ALT above the slope, not above home.
    here = v.state.position_enu_m.copy()
    assert v.commander.takeoff(v.time_s).ok
    assert v.commander.arm(v.time_s).ok
    assert fly(v, 20.0, until=lambda v: v.commander.mode == "HOLD") is not None
    assert not v.commander.landed
    assert v.state.height_agl_m == pytest.approx(v.params.MIS_TAKEOFF_ALT, abs=0.3)
    assert v.state.position_enu_m[2] > here[2] + 2.0
    # LAND: descends at MPC_LAND_SPEED (4 m above the slope is below MPC_LAND_ALT2, though
    # higher than that above home), touches down on the slope, lands, disarms.
    assert v.state.position_enu_m[2] > v.params.MPC_LAND_ALT2
    assert v.commander.set_mode(v.time_s, "LAND").ok
    seen = []
    fly(v, 30.0, until=lambda v: seen.append(v.state.velocity_enu_mps[2]) or not v.commander.armed)
    assert not v.commander.armed and v.commander.landed
    assert min(seen) > -v.params.MPC_LAND_SPEED - 0.15
    assert v.state.position_enu_m[2] == pytest.approx(terrain(*v.state.position_enu_m[:2]), abs=1e-9)
    assert np.hypot(*(v.state.position_enu_m[:2] - here[:2])) < 0.5


def test_an_explicit_takeoff_altitude_under_the_terrain_is_raised_above_it():
    terrain = _slope()
    v = SimVehicle(seed=6, terrain=terrain)
    v.airframe.terrain = lambda x, y: 3.0 + terrain(x, y)      # home itself is on a 3 m step
    v.airframe.state.position_enu_m[2] = v.airframe.state.ground_z_m = 3.0
    assert v.commander.arm(v.time_s).ok
    assert v.commander.takeoff(v.time_s, 2.0).ok               # 2 m above home: under this ground
    assert fly(v, 20.0, until=lambda v: v.commander.mode == "HOLD") is not None
    assert v.state.height_agl_m == pytest.approx(1.0, abs=0.3)


def test_flat_by_default():
    v = SimVehicle(seed=1)
    assert v.airframe.terrain(100.0, -50.0) == 0.0


def test_stamps_epoch_is_taken_when_the_paced_loop_starts_not_when_the_runner_was_built():
    """Sensor stamps (epoch_ns + sim time) must match wall-clock stamps of services at 1x: an
    epoch taken while renderers were still being set up put every scan ~0.5 s in the past."""
    import time

    runner = SimVehicleRunner(SimVehicle(seed=0), speed=1.0)
    built = runner.epoch_ns
    time.sleep(0.3)                        # setting up renderers, spawning processes...
    runner.start()
    try:
        time.sleep(0.2)
        lag_s = (time.time_ns() - (runner.epoch_ns + runner.now_ns())) * 1e-9
    finally:
        runner.stop()
    assert runner.epoch_ns - built >= 0.25e9
    assert abs(lag_s) < 0.1, f"stamps {lag_s:.3f} s behind the wall clock"
