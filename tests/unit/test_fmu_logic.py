"""fmu logic (services/fmu/logic.py): MAVLink messages in -> ENU/FLU schemas out, setpoints and
vision odometry ENU/FLU -> NED/FRD MAVLink fields back, and COMMAND_ACK matching.

Messages are real pymavlink message objects; outgoing field dicts are packed into real
MAVLink messages, so a wrong field name or type fails here rather than on the wire.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import (
    BatteryState, HomePosition, Imu, LandedState, LocalPosition, NDArray, Odometry, Pose, Quaternion, SchemaError,
    TrajectorySetpoint, Twist, Vector3, VehicleStatus, decode, encode,
)
from aeroperception.services.fmu.logic import (
    IGNORE_ACC, IGNORE_POS, IGNORE_VEL, IGNORE_YAW, IGNORE_YAW_RATE, CommandWaiter, Telemetry,
    ack_name, highres_imu_to_imu, hold_target, home_position_from_mavlink, odometry_fields, parse_global_origin,
    setpoint_target,
)

MAV = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
DISARMED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
PX4_OFFBOARD = 6 << 16
PX4_HOLD = (4 << 16) | (3 << 24)
PX4_LAND = 0x06040000


def packs(msg) -> None:
    """The message encodes as MAVLink v2 and decodes back to the same type."""
    buf = msg.pack(MAV)
    back = mavlink.MAVLink(None).decode(bytearray(buf))
    assert back.get_type() == msg.get_type()


def setpoint_msg(fields: dict):
    return mavlink.MAVLink_set_position_target_local_ned_message(
        time_boot_ms=0, target_system=1, target_component=1, **fields)


def vec(v: Vector3) -> list[float]:
    return v.to_array().tolist()


# ================================================================ setpoints (ENU -> NED)

def test_velocity_only_setpoint_ignores_position_acceleration_and_yaw_rate():
    sp = TrajectorySetpoint(velocity_valid=True, yaw_valid=True,
                            position_m=Vector3(x=99.0, y=99.0, z=99.0),  # feed-forward, not used
                            velocity_mps=Vector3(x=1.0, y=2.0, z=3.0), yaw_rad=0.0)
    f = setpoint_target(sp)
    mask = f["type_mask"]
    assert mask & IGNORE_POS == IGNORE_POS
    assert mask & IGNORE_VEL == 0
    assert mask & IGNORE_ACC == IGNORE_ACC
    assert mask & IGNORE_YAW == 0
    assert mask & IGNORE_YAW_RATE == IGNORE_YAW_RATE
    assert mask == IGNORE_POS | IGNORE_ACC | IGNORE_YAW_RATE
    assert f["coordinate_frame"] == mavlink.MAV_FRAME_LOCAL_NED
    packs(setpoint_msg(f))


def test_setpoint_velocity_enu_1_2_3_is_ned_2_1_minus_3():
    # East 1, North 2, Up 3  ->  North 2, East 1, Down -3
    sp = TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1.0, y=2.0, z=3.0))
    f = setpoint_target(sp)
    assert (f["vx"], f["vy"], f["vz"]) == (2.0, 1.0, -3.0)


@pytest.mark.parametrize(("yaw_enu", "yaw_ned"), [
    (0.0, math.pi / 2),            # facing East
    (math.pi / 2, 0.0),            # facing North
    (math.pi, -math.pi / 2),       # facing West (= +3pi/2, wrapped)
    (-math.pi / 2, -math.pi),      # facing South (pi wraps to -pi)
    (math.pi / 4, math.pi / 4),    # North-East is the fixed point
])
def test_setpoint_yaw_enu_to_ned(yaw_enu, yaw_ned):
    f = setpoint_target(TrajectorySetpoint(yaw_valid=True, yaw_rad=yaw_enu))
    assert math.cos(f["yaw"]) == pytest.approx(math.cos(yaw_ned), abs=1e-12)
    assert math.sin(f["yaw"]) == pytest.approx(math.sin(yaw_ned), abs=1e-12)
    assert -math.pi <= f["yaw"] <= math.pi


def test_hold_sets_position_and_zero_velocity():
    f = hold_target(np.array([1.0, 2.0, 3.0]), 0.0)   # ENU: 1 m East, 2 m North, 3 m up
    assert f["type_mask"] == IGNORE_ACC | IGNORE_YAW_RATE  # position, velocity and yaw all used
    assert (f["x"], f["y"], f["z"]) == (2.0, 1.0, -3.0)
    assert (f["vx"], f["vy"], f["vz"]) == (0.0, 0.0, 0.0)
    assert f["yaw"] == pytest.approx(math.pi / 2)
    packs(setpoint_msg(f))


@pytest.mark.parametrize("sp", [
    TrajectorySetpoint(velocity_valid=True, yaw_valid=False, yaw_rad=1.0),
    TrajectorySetpoint(velocity_valid=True, yaw_valid=True, yaw_rad=float("nan")),
], ids=["yaw-not-valid", "yaw-nan"])
def test_invalid_yaw_sets_the_ignore_yaw_bit(sp):
    f = setpoint_target(sp)
    assert f["type_mask"] & IGNORE_YAW
    assert math.isfinite(f["yaw"])                     # never put NaN on the wire


def test_yaw_rate_is_negated_and_used_when_valid():
    f = setpoint_target(TrajectorySetpoint(velocity_valid=True, yaw_rate_valid=True, yaw_rate_radps=0.5))
    assert f["type_mask"] & IGNORE_YAW_RATE == 0
    assert f["yaw_rate"] == -0.5                       # CCW (ENU, about Up) = CW-negative about Down


def test_nothing_valid_ignores_everything_but_sends_finite_numbers():
    f = setpoint_target(TrajectorySetpoint(position_m=Vector3(x=float("nan"))))
    assert f["type_mask"] == IGNORE_POS | IGNORE_VEL | IGNORE_ACC | IGNORE_YAW | IGNORE_YAW_RATE
    assert all(math.isfinite(f[k]) for k in ("x", "y", "z", "vx", "vy", "vz", "yaw", "yaw_rate"))


@pytest.mark.parametrize(("valid", "used_bits"), [
    ("position_valid", IGNORE_POS), ("velocity_valid", IGNORE_VEL), ("acceleration_valid", IGNORE_ACC),
    ("yaw_valid", IGNORE_YAW), ("yaw_rate_valid", IGNORE_YAW_RATE),
])
def test_type_mask_uses_exactly_the_fields_marked_valid(valid, used_bits):
    everything = IGNORE_POS | IGNORE_VEL | IGNORE_ACC | IGNORE_YAW | IGNORE_YAW_RATE
    f = setpoint_target(TrajectorySetpoint(**{valid: True}))
    assert f["type_mask"] == everything & ~used_bits
    assert not f["type_mask"] & mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET   # acceleration, not force
    packs(setpoint_msg(f))


def test_acceleration_feed_forward_is_sent_in_ned():
    # East 1, North 2, Up 3 m/s^2 -> North 2, East 1, Down -3 alongside the velocity it feeds
    sp = TrajectorySetpoint(velocity_valid=True, acceleration_valid=True, velocity_mps=Vector3(x=0.5),
                            acceleration_mps2=Vector3(x=1.0, y=2.0, z=3.0))
    f = setpoint_target(sp)
    assert f["type_mask"] == IGNORE_POS | IGNORE_YAW | IGNORE_YAW_RATE
    assert (f["afx"], f["afy"], f["afz"]) == (2.0, 1.0, -3.0)
    assert (f["vx"], f["vy"], f["vz"]) == (0.0, 0.5, 0.0)


def test_acceleration_not_valid_is_ignored_and_sent_as_zeros():
    f = setpoint_target(TrajectorySetpoint(velocity_valid=True, acceleration_mps2=Vector3(x=math.nan, y=5.0)))
    assert f["type_mask"] & IGNORE_ACC == IGNORE_ACC
    assert (f["afx"], f["afy"], f["afz"]) == (0.0, 0.0, 0.0)


# ================================================================ telemetry (NED -> ENU)

def test_local_position_ned_becomes_enu_position_and_velocity():
    tm = Telemetry()
    m = mavlink.MAVLink_local_position_ned_message(time_boot_ms=1000, x=1.0, y=2.0, z=-3.0,
                                                   vx=0.5, vy=-1.0, vz=0.25)
    lp = tm.on_local_position(m, stamp_ns=123)
    assert isinstance(lp, LocalPosition)
    assert vec(lp.position_m) == [2.0, 1.0, 3.0]
    assert vec(lp.velocity_mps) == [-1.0, 0.5, -0.25]
    assert lp.position_valid and lp.velocity_valid
    assert lp.header.stamp_ns == 123 and lp.header.frame_id == "map"
    assert tm.have_position
    np.testing.assert_allclose(tm.position_m, [2.0, 1.0, 3.0])


@pytest.mark.parametrize(("custom_mode", "name"), [
    (PX4_OFFBOARD, "OFFBOARD"), (PX4_HOLD, "HOLD"), (PX4_LAND, "LAND"),
    ((4 << 16) | (5 << 24), "RTL"), ((4 << 16) | (2 << 24), "TAKEOFF"), (3 << 16, "POSCTL"),
])
@pytest.mark.parametrize("armed", [True, False])
def test_px4_heartbeat_decodes_mode_name_and_armed_flag(custom_mode, name, armed):
    tm = Telemetry()
    hb = mavlink.MAVLink_heartbeat_message(
        type=mavlink.MAV_TYPE_QUADROTOR, autopilot=mavlink.MAV_AUTOPILOT_PX4,
        base_mode=ARMED if armed else DISARMED, custom_mode=custom_mode,
        system_status=mavlink.MAV_STATE_ACTIVE, mavlink_version=3)
    st = tm.on_heartbeat(hb)
    assert isinstance(st, VehicleStatus)
    assert (st.nav_state, st.armed, st.custom_mode, st.autopilot) == (name, armed, custom_mode, "px4")
    assert not st.failsafe
    vs = tm.vehicle_state(1, connected=True)
    assert (vs.flight_mode, vs.armed) == (name, armed)


def test_land_custom_mode_value():
    assert PX4_LAND == (4 << 16) | (6 << 24)


def test_critical_system_status_is_a_failsafe():
    tm = Telemetry()
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, ARMED,
                                           PX4_HOLD, mavlink.MAV_STATE_CRITICAL, 3)
    assert tm.on_heartbeat(hb).failsafe


def test_status_is_periodic_and_a_changed_heartbeat_goes_out_at_once():
    """fmu/out/vehicle_status: every periodic tick (5 Hz, the FC's heartbeat is 1 Hz) carries the
    latest telemetry; a heartbeat publishes only when it changed the status (mode, arming)."""
    tm = Telemetry()
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, DISARMED,
                                           PX4_HOLD, mavlink.MAV_STATE_STANDBY, 3)
    tm.on_heartbeat(hb)
    first = tm.status_to_publish(10, periodic=False)
    assert first is not None and first.header.stamp_ns == 10 and first.nav_state == "HOLD"
    tm.on_heartbeat(hb)
    assert tm.status_to_publish(20, periodic=False) is None          # unchanged heartbeat: no extra message
    tick = tm.status_to_publish(30, periodic=True)
    assert tick is not None and tick.header.stamp_ns == 30            # the tick always publishes
    tm.on_extended_sys_state(mavlink.MAVLink_extended_sys_state_message(0, mavlink.MAV_LANDED_STATE_ON_GROUND))
    assert tm.status_to_publish(40, periodic=True).landed_state == LandedState.ON_GROUND
    hb.base_mode, hb.custom_mode = ARMED, PX4_OFFBOARD
    tm.on_heartbeat(hb)
    armed = tm.status_to_publish(50, periodic=False)
    assert armed is not None and (armed.armed, armed.nav_state) == (True, "OFFBOARD")


def test_ardupilot_heartbeat_switches_the_mode_map():
    tm = Telemetry()
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           ARMED, 4, mavlink.MAV_STATE_ACTIVE, 3)  # 4 = GUIDED
    st = tm.on_heartbeat(hb)
    assert (st.autopilot, st.nav_state) == ("ardupilot", "OFFBOARD")
    assert tm.vehicle_state(1, True).estimator_name == "ardupilot-ekf"


@pytest.mark.parametrize(("mav", "ours"), [
    (mavlink.MAV_LANDED_STATE_UNDEFINED, LandedState.UNDEFINED),
    (mavlink.MAV_LANDED_STATE_ON_GROUND, LandedState.ON_GROUND),
    (mavlink.MAV_LANDED_STATE_IN_AIR, LandedState.IN_AIR),
    (mavlink.MAV_LANDED_STATE_TAKEOFF, LandedState.TAKEOFF),
    (mavlink.MAV_LANDED_STATE_LANDING, LandedState.LANDING),
    (77, LandedState.UNDEFINED),
])
def test_extended_sys_state_landed_state_mapping(mav, ours):
    tm = Telemetry()
    tm.on_extended_sys_state(mavlink.MAVLink_extended_sys_state_message(vtol_state=0, landed_state=mav))
    assert tm.landed_state == ours
    assert tm.vehicle_state(1, True).landed_state == ours
    assert tm.vehicle_status().landed_state == ours


def sys_status(voltage_mv, current_ca, remaining_pct):
    return mavlink.MAVLink_sys_status_message(0, 0, 0, 0, voltage_mv, current_ca, remaining_pct, 0, 0, 0, 0, 0, 0)


def test_sys_status_battery_fraction_voltage_and_current():
    tm = Telemetry()
    tm.on_sys_status(sys_status(12_600, 150, 76))
    assert tm.battery_remaining == pytest.approx(0.76)
    assert tm.battery_voltage_v == pytest.approx(12.6)
    assert tm.battery_current_a == pytest.approx(1.5)
    vs = tm.vehicle_state(1, True)
    assert vs.battery_remaining == pytest.approx(0.76) and vs.battery_voltage_v == pytest.approx(12.6)


def test_sys_status_unknown_battery_values_stay_none():
    tm = Telemetry()
    tm.on_sys_status(sys_status(0xFFFF, -1, -1))
    assert (tm.battery_remaining, tm.battery_voltage_v, tm.battery_current_a) == (None, None, None)
    vs = tm.vehicle_state(1, True)
    assert vs.battery_remaining is None and vs.battery_voltage_v is None


def test_battery_status_sums_valid_cells_and_reports_the_fraction():
    tm = Telemetry()
    cells = [4200, 4150, 4100] + [0xFFFF] * 7
    m = mavlink.MAVLink_battery_status_message(id=0, battery_function=0, type=0, temperature=2550,
                                               voltages=cells, current_battery=1200, current_consumed=-1,
                                               energy_consumed=-1, battery_remaining=64)
    b = tm.on_battery_status(m, stamp_ns=5)
    assert isinstance(b, BatteryState)
    assert b.voltage_v == pytest.approx(12.45)
    assert b.current_a == pytest.approx(12.0)
    assert b.remaining_fraction == pytest.approx(0.64)
    assert b.temperature_c == pytest.approx(25.5)
    assert b.cell_count == 3


def test_battery_status_with_unknown_temperature_and_remaining():
    tm = Telemetry()
    m = mavlink.MAVLink_battery_status_message(0, 0, 0, 0x7FFF, [11_100] + [0xFFFF] * 9, -1, -1, -1, -1)
    b = tm.on_battery_status(m, stamp_ns=5)
    assert b.temperature_c is None and b.remaining_fraction is None and b.current_a is None
    assert b.voltage_v == pytest.approx(11.1)


def test_attitude_heading_north_level_is_enu_yaw_pi_over_2():
    tm = Telemetry()
    m = mavlink.MAVLink_attitude_quaternion_message(time_boot_ms=0, q1=1.0, q2=0.0, q3=0.0, q4=0.0,
                                                    rollspeed=0.1, pitchspeed=0.2, yawspeed=0.3)
    att = tm.on_attitude_quaternion(m, stamp_ns=9)
    assert tm.yaw_rad == pytest.approx(math.pi / 2)
    assert vec(att.angular_velocity_radps) == pytest.approx([0.1, -0.2, -0.3])
    q = att.orientation
    np.testing.assert_allclose([q.w, q.x, q.y, q.z], [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-12)
    vs = tm.vehicle_state(10, connected=True)
    assert vs.yaw_rad == pytest.approx(math.pi / 2)
    assert vs.roll_rad == pytest.approx(0.0, abs=1e-12) and vs.pitch_rad == pytest.approx(0.0, abs=1e-12)
    # the local position message carries the same yaw afterwards
    lp = tm.on_local_position(mavlink.MAVLink_local_position_ned_message(0, 0, 0, 0, 0, 0, 0), 11)
    assert lp.yaw_rad == pytest.approx(math.pi / 2)


def test_vehicle_state_reports_a_stale_link_with_zero_confidence():
    tm = Telemetry()
    assert tm.vehicle_state(1, connected=False).confidence == 0.0
    assert tm.vehicle_state(1, connected=True).confidence == 1.0
    assert not tm.vehicle_state(1, connected=False).connected


# ================================================================ home (HOME_POSITION -> HomePosition)

def home_msg(lat_e7=473977420, lon_e7=85455940, alt_mm=488000, x=0.0, y=0.0, z=0.0):
    """HOME_POSITION as PX4 sends it: geodetic home + home in the local NED frame."""
    return mavlink.MAVLink_home_position_message(
        latitude=lat_e7, longitude=lon_e7, altitude=alt_mm, x=x, y=y, z=z, q=[1.0, 0.0, 0.0, 0.0],
        approach_x=0.0, approach_y=0.0, approach_z=0.0, time_usec=5_000_000)


def test_home_position_geodetic_and_local_ned_becomes_enu():
    # home 3 m North, 4 m East, 0.5 m below the local origin (NED z = +0.5)
    m = home_msg(x=3.0, y=4.0, z=0.5)
    packs(m)
    tm = Telemetry()
    home = tm.on_home_position(m, stamp_ns=77)
    assert isinstance(home, HomePosition) and tm.home == home
    assert home.latitude_deg == pytest.approx(47.397742, abs=1e-9)
    assert home.longitude_deg == pytest.approx(8.545594, abs=1e-9)
    assert home.altitude_amsl_m == pytest.approx(488.0)
    assert vec(home.position_m) == [4.0, 3.0, -0.5]        # ENU: East 4, North 3, Up -0.5
    assert home.header.stamp_ns == 77 and home.header.frame_id == "map"


def test_home_position_southern_western_hemisphere_and_non_finite_local_position():
    home = home_position_from_mavlink(home_msg(-338688197, -1512093048, -12345, x=math.nan), 1)
    assert (home.latitude_deg, home.longitude_deg) == pytest.approx((-33.8688197, -151.2093048), abs=1e-9)
    assert home.altitude_amsl_m == pytest.approx(-12.345)
    assert vec(home.position_m) == [0.0, 0.0, 0.0]          # unknown local position: the origin


def test_home_position_without_a_home_is_ignored():
    tm = Telemetry()
    good = tm.on_home_position(home_msg(), 1)
    assert tm.on_home_position(home_msg(0, 0, 0), 2) is None            # "no home yet" (lat = lon = 0)
    assert tm.on_home_position(home_msg(lat_e7=950000000), 3) is None   # latitude 95 deg
    assert tm.home == good


# ================================================================ IMU (FRD -> FLU)

def test_highres_imu_level_vehicle_specific_force_is_plus_g_up_in_flu():
    m = mavlink.MAVLink_highres_imu_message(
        time_usec=1, xacc=0.0, yacc=0.0, zacc=-9.81, xgyro=0.1, ygyro=0.2, zgyro=0.3,
        xmag=0, ymag=0, zmag=0, abs_pressure=0, diff_pressure=0, pressure_alt=0, temperature=20,
        fields_updated=0x3F)
    imu = highres_imu_to_imu(m, stamp_ns=42)
    assert isinstance(imu, Imu)
    assert vec(imu.linear_acceleration_mps2) == pytest.approx([0.0, 0.0, 9.81])
    assert vec(imu.angular_velocity_radps) == pytest.approx([0.1, -0.2, -0.3])
    assert imu.header.stamp_ns == 42 and imu.header.frame_id == "base_link"


def test_highres_imu_right_side_acceleration_becomes_minus_y_in_flu():
    m = mavlink.MAVLink_highres_imu_message(1, 1.0, 2.0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    imu = highres_imu_to_imu(m, stamp_ns=0)
    assert vec(imu.linear_acceleration_mps2) == pytest.approx([1.0, -2.0, 9.81])


# ================================================================ vision odometry (ENU/FLU -> NED/FRD)

IU = np.triu_indices(6)


def urt_to_cov(urt) -> np.ndarray:
    c = np.zeros((6, 6))
    c[IU] = urt
    return c + np.triu(c, 1).T


def vio_odometry(pose_cov=None, twist_cov=None) -> Odometry:
    return Odometry(
        pose=Pose(position=Vector3(x=1.0, y=2.0, z=3.0), orientation=Quaternion.from_yaw(0.0)),  # facing East
        twist=Twist(linear=Vector3(x=1.0, y=0.5, z=0.2), angular=Vector3(x=0.01, y=0.02, z=0.03)),
        pose_covariance=None if pose_cov is None else NDArray.from_numpy(pose_cov),
        twist_covariance=None if twist_cov is None else NDArray.from_numpy(twist_cov))


def test_odometry_fields_are_a_local_frd_pose_and_body_frd_velocity_with_vision_estimator():
    """LOCAL_FRD, not LOCAL_NED: the VIO's odom frame starts at its own heading; PX4 fuses a LOCAL_NED
    pose as North-aligned but rotates a LOCAL_FRD one onto its heading (mavlink_receiver -> EKF2)."""
    f = odometry_fields(vio_odometry(), time_usec=1_000_000)
    assert (f["x"], f["y"], f["z"]) == (2.0, 1.0, -3.0)
    # FLU forward/left/up body velocity -> FRD forward/right/down
    assert (f["vx"], f["vy"], f["vz"]) == (1.0, -0.5, -0.2)
    assert (f["rollspeed"], f["pitchspeed"], f["yawspeed"]) == (0.01, -0.02, -0.03)
    w, x, y, z = f["q"]                                # facing East = NED heading +90 deg
    assert 2 * math.atan2(z, w) == pytest.approx(math.pi / 2) and abs(x) < 1e-12 and abs(y) < 1e-12
    assert f["estimator_type"] == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert f["frame_id"] == mavlink.MAV_FRAME_LOCAL_FRD
    assert f["child_frame_id"] == mavlink.MAV_FRAME_BODY_FRD
    assert f["time_usec"] == 1_000_000 and f["reset_counter"] == 0
    assert f["quality"] == 0                           # the estimator gave none: MAVLink's "unknown"
    packs(mavlink.MAVLink_odometry_message(**f))


def test_odometry_reset_counter_and_quality_are_refused_out_of_range_and_optional_when_missing():
    plain = msgpack.unpackb(encode(vio_odometry()))
    for field, bad in (("reset_counter", -1), ("quality_pct", 0), ("quality_pct", 101)):
        with pytest.raises(SchemaError, match=field):
            decode(msgpack.packb({**plain, field: bad}), Odometry)
    for field, good in (("reset_counter", 7), ("quality_pct", 1), ("quality_pct", 100)):
        assert getattr(decode(msgpack.packb({**plain, field: good}), Odometry), field) == good
    old = decode(msgpack.packb({k: v for k, v in plain.items() if k not in ("reset_counter", "quality_pct")}), Odometry)
    assert (old.reset_counter, old.quality_pct) == (0, None)       # from a publisher without them


def test_odometry_carries_the_estimators_reset_counter_wrapping_at_a_byte_and_its_quality():
    """EKF2 re-aligns to the vision pose when reset_counter changes and gates on quality
    (EKF2_EV_QMIN): both are the estimator's, not constants."""
    for counter, quality, want in ((3, 87, (3, 87)), (256 + 4, 1, (4, 1)), (0, 100, (0, 100))):
        odom = vio_odometry()
        odom.reset_counter, odom.quality_pct = counter, quality
        f = odometry_fields(odom, time_usec=0)
        assert (f["reset_counter"], f["quality"]) == want
        packs(mavlink.MAVLink_odometry_message(**f))


def test_global_origin_is_lat_lon_alt_or_nothing_and_refused_naming_the_parameter():
    assert parse_global_origin("") is None
    assert parse_global_origin("47.397742, 8.545594,489.4") == (47.397742, 8.545594, 489.4)
    for bad in ("47.3,8.5", "north,8.5,400", "91,8.5,400", "47,8.5,nan"):
        with pytest.raises(ValueError, match="global_origin"):
            parse_global_origin(bad)


def test_odometry_without_covariance_says_unknown_with_a_leading_nan():
    f = odometry_fields(vio_odometry(), time_usec=0)
    for key in ("pose_covariance", "velocity_covariance"):
        assert len(f[key]) == 21 and math.isnan(f[key][0])


def test_odometry_covariance_is_a_valid_21_element_ned_frd_triangle():
    pose = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    pose[0, 1] = pose[1, 0] = 0.5    # x_E, y_N
    pose[0, 2] = pose[2, 0] = 0.25   # x_E, z_Up
    pose[3, 4] = pose[4, 3] = 0.05   # roll, pitch (FLU)
    twist = np.diag([0.4, 0.5, 0.6, 0.01, 0.02, 0.03])
    twist[0, 1] = twist[1, 0] = 0.1  # forward, left
    f = odometry_fields(vio_odometry(pose, twist), time_usec=0)

    for key in ("pose_covariance", "velocity_covariance"):
        assert len(f[key]) == 21 and all(math.isfinite(v) for v in f[key])
    p_ned = urt_to_cov(f["pose_covariance"])
    # hand-worked: N/E swap the variances, x-y coupling survives, E-Up becomes E-Down (sign flips)
    assert np.diag(p_ned).tolist() == pytest.approx([2.0, 1.0, 3.0, 0.1, 0.2, 0.3])
    assert p_ned[0, 1] == pytest.approx(0.5)        # N,E
    assert p_ned[1, 2] == pytest.approx(-0.25)      # E,Down
    assert p_ned[0, 2] == pytest.approx(0.0)
    assert p_ned[3, 4] == pytest.approx(-0.05)      # roll, pitch (FRD: pitch sign flips)
    t_frd = urt_to_cov(f["velocity_covariance"])
    assert np.diag(t_frd).tolist() == pytest.approx([0.4, 0.5, 0.6, 0.01, 0.02, 0.03])
    assert t_frd[0, 1] == pytest.approx(-0.1)       # forward, right
    for c in (p_ned, t_frd):
        assert np.linalg.eigvalsh(c).min() > 0
    packs(mavlink.MAVLink_odometry_message(**f))


# ================================================================ COMMAND_ACK matching

def ack(command, result):
    return mavlink.MAVLink_command_ack_message(command=command, result=result)


def test_command_waiter_matches_the_ack_by_command_id():
    w = CommandWaiter()
    arm_ev, arm_box = w.expect(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    mode_ev, mode_box = w.expect(mavlink.MAV_CMD_DO_SET_MODE)

    w.on_ack(ack(mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_RESULT_ACCEPTED))  # nobody waits for it
    assert not arm_ev.is_set() and not mode_ev.is_set()

    w.on_ack(ack(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED))
    assert mode_ev.is_set() and mode_box == [mavlink.MAV_RESULT_DENIED]
    assert not arm_ev.is_set() and arm_box == []

    w.on_ack(ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED))
    assert arm_ev.wait(0) and arm_box == [mavlink.MAV_RESULT_ACCEPTED]


def test_command_waiter_takes_one_ack_per_wait():
    w = CommandWaiter()
    ev, box = w.expect(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    w.on_ack(ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED))
    w.on_ack(ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_FAILED))  # late duplicate
    assert box == [mavlink.MAV_RESULT_ACCEPTED]
    ev2, box2 = w.expect(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    assert not ev2.is_set()


def test_command_waiter_a_new_wait_replaces_the_old_one():
    w = CommandWaiter()
    old_ev, _ = w.expect(mavlink.MAV_CMD_DO_SET_MODE)
    new_ev, new_box = w.expect(mavlink.MAV_CMD_DO_SET_MODE)
    w.on_ack(ack(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_ACCEPTED))
    assert new_ev.is_set() and new_box == [mavlink.MAV_RESULT_ACCEPTED]
    assert not old_ev.is_set()


@pytest.mark.parametrize(("result", "name"), [
    (mavlink.MAV_RESULT_ACCEPTED, "ACCEPTED"), (mavlink.MAV_RESULT_DENIED, "DENIED"),
    (mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "TEMPORARILY_REJECTED"), (250, "250"),
])
def test_ack_names(result, name):
    assert ack_name(result) == name


# ================================================================ offboard arbiter (services/fmu/offboard.py)

from aeroperception.schemas import Header  # noqa: E402
from aeroperception.services.fmu.link import RebootWatch, is_autopilot_heartbeat  # noqa: E402
from aeroperception.services.fmu.offboard import (  # noqa: E402
    StreamWarmth,
    BRAKE, FOLLOW, HOLD, JERK_REFUSED, PLANNER_SILENT, ArbiterConfig, Envelope, OffboardArbiter,
)
from aeroperception.services.fmu import contract as fmu_contract  # noqa: E402
from aeroperception.services.runtime.config import build  # noqa: E402


def arbiter(**cfg) -> OffboardArbiter:
    """An arbiter with the contract's defaults but for `cfg` (ArbiterConfig's field names)."""
    return OffboardArbiter(build(ArbiterConfig, fmu_contract.PARAMS, **cfg))


def envelope() -> Envelope:
    return build(Envelope, fmu_contract.PARAMS)

STILL = np.zeros(3)


def planner_sp(stamp_ns: int, vx: float = 2.0) -> TrajectorySetpoint:
    return TrajectorySetpoint(header=Header(stamp_ns=stamp_ns), velocity_valid=True, yaw_valid=True,
                              velocity_mps=Vector3(x=vx), yaw_rad=0.0)


def following(resume: int = 3) -> tuple[OffboardArbiter, float]:
    """An arbiter that has just started following (state epoch 1 s), and the time."""
    a = arbiter(timeout_s=0.3, resume_count=resume)
    a.on_state(1_000_000_000, new_session=True)
    t = 0.0
    for i in range(resume):
        t += 0.02
        out = a.on_setpoint(planner_sp(1_000_000_000 + i), t)
    assert out is not None and a.phase == FOLLOW
    return a, t


@pytest.mark.parametrize(("sp", "why"), [
    (TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=math.nan)), "non-finite velocity"),
    (TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=math.inf)), "non-finite velocity"),
    (TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1000.0)), "velocity 1000.0 m/s"),
    (TrajectorySetpoint(position_valid=True, position_m=Vector3(x=5000.0, z=5.0)), "from the origin"),
    (TrajectorySetpoint(position_valid=True, position_m=Vector3(z=5000.0)), "position z"),
    (TrajectorySetpoint(position_valid=True, position_m=Vector3(z=-50.0)), "position z"),
    (TrajectorySetpoint(position_valid=True, position_m=Vector3(y=math.nan)), "non-finite position"),
    (TrajectorySetpoint(velocity_valid=True, acceleration_valid=True, acceleration_mps2=Vector3(z=1e9)), "acceleration"),
    (TrajectorySetpoint(velocity_valid=True, yaw_valid=True, yaw_rad=math.nan), "non-finite yaw"),
    (TrajectorySetpoint(velocity_valid=True, yaw_rate_valid=True, yaw_rate_radps=math.inf), "yaw rate"),
    (TrajectorySetpoint(), "neither position nor velocity"),
    (TrajectorySetpoint(velocity_valid=True, jerk_valid=True, jerk_mps3=Vector3(x=1.0)), "jerk_valid"),
])
def test_envelope_refuses_non_finite_and_out_of_envelope_setpoints(sp, why):
    assert why in envelope().problem(sp)


def test_a_setpoint_with_jerk_marked_valid_is_refused_counted_and_held_with_the_reason():
    a, t = following()
    sp = planner_sp(1_000_000_000)
    sp.jerk_valid, sp.jerk_mps3 = True, Vector3(x=0.5)
    assert a.on_setpoint(sp, t + 0.02) is None
    assert a.counters["setpoints_rejected"] == 1
    assert a.last_rejection == JERK_REFUSED and "no jerk field" in JERK_REFUSED
    assert a.phase == BRAKE and a.reason == f"setpoint rejected: {JERK_REFUSED}"


def test_envelope_checks_acceleration_feed_forward_only_when_valid():
    ok = TrajectorySetpoint(velocity_valid=True, acceleration_valid=True, acceleration_mps2=Vector3(x=3.0))
    assert envelope().problem(ok) == ""
    assert envelope().problem(TrajectorySetpoint(velocity_valid=True, acceleration_mps2=Vector3(x=math.nan))) == ""


def test_envelope_ignores_unused_fields_and_accepts_the_planners_setpoints():
    sp = TrajectorySetpoint(velocity_valid=True, yaw_valid=True, velocity_mps=Vector3(x=2.0),
                            position_m=Vector3(x=math.nan, y=1e9), yaw_rad=1.0)  # position unused
    assert envelope().problem(sp) == ""
    assert envelope().problem(TrajectorySetpoint(position_valid=True, velocity_valid=True,
                                                 position_m=Vector3(x=900.0, z=400.0))) == ""


def test_starts_holding_and_follows_only_after_n_fresh_setpoints():
    a = arbiter(resume_count=5)
    phase, sp = a.tick(0.0, STILL, STILL, 0.3)
    assert phase == HOLD and sp.position_valid and a.reason.startswith("waiting")
    a.on_state(1_000, new_session=True)
    outs = [a.on_setpoint(planner_sp(1_000 + i), 0.02 * i) for i in range(5)]
    assert outs[:4] == [None] * 4 and outs[4] is not None and a.phase == FOLLOW
    assert a.tick(0.1, STILL, STILL, 0.0)[0] == FOLLOW


def test_hysteresis_a_late_setpoint_brakes_and_one_fresh_setpoint_does_not_resume():
    a, t = following(resume=3)
    phase, _ = a.tick(t + 0.31, STILL, np.array([2.0, 0, 0]), 0.0)   # 310 ms late
    assert phase == BRAKE and a.reason == PLANNER_SILENT
    t += 0.32
    assert a.on_setpoint(planner_sp(2_000_000_000), t) is None        # 1 of 3
    assert a.on_setpoint(planner_sp(2_000_000_001), t + 0.02) is None  # 2 of 3
    assert a.on_setpoint(planner_sp(2_000_000_002), t + 0.04) is not None
    assert a.phase == FOLLOW and a.counters["follow_resumed"] == 2


def test_hysteresis_streak_restarts_after_a_gap_or_a_rejected_setpoint():
    a, t = following(resume=3)
    a.tick(t + 0.5, STILL, STILL, 0.0)
    t += 0.5
    a.on_setpoint(planner_sp(2_000_000_000), t)
    a.on_setpoint(planner_sp(2_000_000_001), t + 0.02)
    a.on_setpoint(planner_sp(2_000_000_002, vx=math.nan), t + 0.04)  # rejected: streak 0
    assert a.on_setpoint(planner_sp(2_000_000_003), t + 0.06) is None
    assert a.on_setpoint(planner_sp(2_000_000_004), t + 0.08) is None
    assert a.on_setpoint(planner_sp(2_000_000_005), t + 0.50) is None  # gap > timeout: streak 1
    assert a.on_setpoint(planner_sp(2_000_000_006), t + 0.52) is None
    assert a.on_setpoint(planner_sp(2_000_000_007), t + 0.54) is not None


def test_rejected_setpoint_while_following_is_never_forwarded_and_brakes_at_once():
    a, t = following()
    assert a.on_setpoint(planner_sp(2_000_000_000, vx=1000.0), t + 0.02) is None
    assert a.phase == BRAKE and "velocity 1000.0" in a.reason and a.counters["setpoints_rejected"] == 1
    phase, sp = a.tick(t + 0.03, STILL, np.array([2.0, 0, 0]), 0.0)
    assert phase == BRAKE and sp.velocity_valid and not sp.position_valid
    assert sp.velocity_mps.to_array().tolist() == [0.0, 0.0, 0.0]


def test_brake_until_slow_then_hold_where_the_vehicle_stopped():
    a, t = following()
    a.on_planner_health(False, "planner not alive")
    assert a.label() == "holding (planner not alive)"
    pos, vel = np.array([10.0, 0.0, 3.0]), np.array([2.0, 0.0, 0.0])
    for _ in range(40):  # decelerating at 3 m/s^2, 50 Hz
        t += 0.02
        phase, sp = a.tick(t, pos, vel, 0.5)
        if phase == HOLD:
            break
        assert phase == BRAKE and sp.velocity_mps.to_array().tolist() == [0.0, 0.0, 0.0] and sp.yaw_rad == 0.5
        pos = pos + vel * 0.02
        vel = np.maximum(vel - 3.0 * 0.02, 0.0)
    assert phase == HOLD and sp.position_valid
    np.testing.assert_allclose(sp.position_m.to_array(), pos)          # where it stopped, not where it was lost
    assert pos[0] > 10.5 and np.linalg.norm(vel) < 0.15
    assert a.on_setpoint(planner_sp(5_000_000_000), t) is None and a.counters["setpoints_ignored"] == 1


def test_brake_gives_up_after_the_timeout_and_holds_anyway():
    a = arbiter(brake_timeout_s=1.0)
    assert a.tick(0.0, STILL, np.array([5.0, 0, 0]), 0.0)[0] == BRAKE
    assert a.tick(0.9, STILL, np.array([5.0, 0, 0]), 0.0)[0] == BRAKE
    assert a.tick(1.01, np.ones(3), np.array([5.0, 0, 0]), 0.0)[0] == HOLD


def test_setpoints_older_than_this_sessions_first_state_are_stale_never_forwarded():
    """A restarted fmu (or a planner resumed from SIGSTOP) never replays motion planned before."""
    a = arbiter(resume_count=2)
    a.on_state(10_000_000_000, new_session=True)       # fmu's first state after (re)start
    for i in range(20):
        assert a.on_setpoint(planner_sp(9_000_000_000 + i), 0.02 * i) is None
    assert a.counters["setpoints_stale"] == 20 and a.phase != FOLLOW and "stale" in a.reason
    a.on_state(10_020_000_000)
    assert a.on_setpoint(planner_sp(10_000_000_000), 0.5) is None
    assert a.on_setpoint(planner_sp(10_020_000_000), 0.52) is not None
    # while following: an old one (> max_age_s behind the newest state) is dropped, not followed
    a.on_state(11_000_000_000)
    assert a.on_setpoint(planner_sp(10_400_000_000), 0.54) is None and a.counters["setpoints_stale"] == 21
    assert a.on_setpoint(planner_sp(10_600_000_000), 0.56) is not None


def test_link_regained_stops_following_until_fresh_setpoints():
    a, t = following()
    a.on_state(5_000_000_000, new_session=True)
    assert a.phase == BRAKE and "link" in a.reason
    assert a.on_setpoint(planner_sp(4_999_999_999), t + 0.02) is None


def test_planner_health_back_waits_for_fresh_setpoints():
    a, t = following(resume=2)
    a.on_planner_health(False, "planner reports ERROR")
    a.on_planner_health(True, "")
    assert a.phase != FOLLOW and a.label() == "holding"
    assert a.on_setpoint(planner_sp(1_000_000_010), t + 0.02) is None
    assert a.on_setpoint(planner_sp(1_000_000_011), t + 0.04) is not None


# ================================================================ FC reboot and link lock helpers

def test_reboot_watch_heartbeat_gap_and_time_boot_going_back():
    w = RebootWatch(gap_s=2.0)
    assert w.on_heartbeat(0.0) == "" and w.on_heartbeat(1.0) == ""
    assert "no heartbeat for 2.5 s" in w.on_heartbeat(3.5)
    assert w.on_boot_time(60_000) == "" and w.on_boot_time(60_020) == ""
    assert w.on_boot_time(59_900) == ""                    # reordered datagram, not a reboot
    assert "went back" in w.on_boot_time(1_500)
    assert w.on_boot_time(1_520) == ""


@pytest.mark.parametrize(("mav_type", "autopilot", "is_fc"), [
    (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, True),
    (mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, True),
    (mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, False),
    (mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_PX4, False),
    (mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, False),
    (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_INVALID, False),
])
def test_only_an_autopilot_heartbeat_locks_the_link(mav_type, autopilot, is_fc):
    hb = mavlink.MAVLink(None).decode(bytearray(MAV.heartbeat_encode(mav_type, autopilot, 0, 0, 0).pack(MAV)))
    assert is_autopilot_heartbeat(hb) == is_fc


def test_stream_warmth_counts_from_the_last_gap():
    """fmu's OFFBOARD request waits for this: PX4 refuses OFFBOARD until it has had a stream."""
    w = StreamWarmth(max_gap_s=0.5)
    assert w.age_s(0.0) == 0.0                     # never streamed
    for i in range(61):                            # 50 Hz for 1.2 s
        w.sent(10.0 + i * 0.02)
    assert w.age_s(11.2) == pytest.approx(1.2, abs=0.03)
    assert w.age_s(11.8) == 0.0                    # silent for 0.6 s: not running
    w.sent(12.0)                                   # restarted after the gap: counts from here
    w.sent(12.4)
    assert w.age_s(12.4) == pytest.approx(0.4)
