"""Each place ArduCopter answers fmu's input differently from PX4 (services/fmu/ardupilot.py), pinned."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import LandedState, TrajectorySetpoint, Vector3
from aeroperception.services.fmu import ardupilot
from aeroperception.services.fmu.logic import IGNORE_ACC, IGNORE_POS, IGNORE_VEL, IGNORE_YAW_RATE, setpoint_target
from aeroperception.services.mavlink.px4 import Autopilot


def sp(pos=None, vel=None, acc=None) -> TrajectorySetpoint:
    kw = {}
    for name, v in (("position_m", pos), ("velocity_mps", vel), ("acceleration_mps2", acc)):
        if v is not None:
            kw[name] = Vector3.from_array(np.array(v, dtype=float))
            kw[name.split("_")[0] + "_valid"] = True
    return TrajectorySetpoint(**kw)


# -------------------------------------------------------------- 1. masks


def test_position_with_acceleration_but_no_velocity_drops_the_acceleration():
    """ArduCopter re-initialises GUIDED (stops) on pos+acc without vel; PX4 takes it as feed-forward."""
    f = setpoint_target(sp(pos=[1, 2, 3], acc=[0.5, 0, 0]))
    assert not f["type_mask"] & IGNORE_ACC and f["afy"] == 0.5      # what PX4 gets
    a = ardupilot.adapt_target(f)
    assert a["type_mask"] & IGNORE_ACC and (a["afx"], a["afy"], a["afz"]) == (0.0, 0.0, 0.0)
    assert a["type_mask"] & IGNORE_VEL and not a["type_mask"] & IGNORE_POS
    assert (a["x"], a["y"], a["z"]) == (f["x"], f["y"], f["z"])


def test_the_combinations_arducopter_accepts_go_through_unchanged():
    for s in (sp(pos=[1, 2, 3]), sp(vel=[1, 0, 0]), sp(acc=[0, 1, 0]), sp(pos=[1, 2, 3], vel=[1, 0, 0]),
              sp(pos=[1, 2, 3], vel=[1, 0, 0], acc=[0, 0, 1]), sp(vel=[1, 0, 0], acc=[0, 0, 1])):
        f = setpoint_target(s)
        assert ardupilot.adapt_target(f) == f


def test_yaw_rate_bits_are_left_alone():
    f = setpoint_target(sp(pos=[0, 0, 5]))
    assert f["type_mask"] & IGNORE_YAW_RATE
    assert ardupilot.setpoint_mask(f["type_mask"]) == f["type_mask"]


# -------------------------------------------------------------- 2. take-off


def takeoff(t, now_s=0.0, **kw):
    args = dict(armed=True, mode="OFFBOARD", landed_state=LandedState.ON_GROUND, vehicle_up_m=0.0, setpoint_up_m=1.0)
    return t.command(now_s, **(args | kw))


def test_armed_on_the_ground_in_guided_a_climb_sends_nav_takeoff_instead_of_the_setpoint():
    t = ardupilot.GuidedTakeoff()
    forward, cmd = takeoff(t)
    assert forward is False and cmd is not None
    assert cmd[6] == ardupilot.TAKEOFF_CLEAR_M and math.isnan(cmd[3])     # altitude above home, yaw unchanged
    assert t.sent == 1


def test_nav_takeoff_is_resent_at_most_once_a_second_and_setpoints_wait():
    t = ardupilot.GuidedTakeoff()
    takeoff(t, now_s=10.0)
    assert takeoff(t, now_s=10.5) == (False, None)
    forward, cmd = takeoff(t, now_s=11.1)
    assert forward is False and cmd is not None and t.sent == 2


def test_in_the_air_or_not_climbing_or_not_guided_the_setpoint_goes_through():
    t = ardupilot.GuidedTakeoff()
    assert takeoff(t, landed_state=LandedState.IN_AIR) == (True, None)
    assert takeoff(t, setpoint_up_m=0.1) == (True, None)             # a hold on the ground
    assert takeoff(t, setpoint_up_m=None) == (True, None)            # velocity-only
    assert takeoff(t, mode="HOLD") == (True, None)
    assert takeoff(t, armed=False) == (True, None)
    assert takeoff(t, landed_state=LandedState.UNDEFINED) == (True, None)   # unknown: as PX4
    assert t.sent == 0


def test_a_climb_rate_alone_also_asks_for_the_takeoff():
    """The planner's first set-points start where the vehicle is, climbing: velocity up, position level."""
    t = ardupilot.GuidedTakeoff()
    forward, cmd = takeoff(t, setpoint_up_m=0.05, setpoint_up_mps=0.5)
    assert forward is False and cmd is not None
    assert takeoff(t, now_s=5.0, setpoint_up_m=0.0, setpoint_up_mps=0.0) == (True, None)


def test_takeoff_param7_is_above_home_for_ardupilot_and_amsl_for_px4():
    ap = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    px4 = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_PX4)
    assert ap.takeoff_param7(5.0, 488.0) == 5.0 and px4.takeoff_param7(5.0, 488.0) == 493.0


def test_guided_is_offboard_and_land_is_land():
    ap = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert ap.set_mode_params("OFFBOARD")[1] == 4 and ap.mode_name(4) == "OFFBOARD"
    assert ap.set_mode_params("LAND")[1] == 9 and ap.set_mode_params("HOLD")[1] == 5


# -------------------------------------------------------------- 3. ready to arm


def status(present: int, health: int):
    return SimpleNamespace(onboard_control_sensors_present=present, onboard_control_sensors_health=health)


def test_prearm_ok_only_when_arducopter_reports_its_checks_present_and_healthy():
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert ardupilot.prearm_ok(status(bit, bit))
    assert not ardupilot.prearm_ok(status(bit, 0))          # EKF3 not yet on GPS
    assert not ardupilot.prearm_ok(status(0, 0))            # an FC that does not report it


def test_ready_to_arm_needs_the_prearm_bit_and_ekf3_on_gps():
    assert ardupilot.ekf_uses_gps("EKF3 IMU0 is using GPS") and ardupilot.ekf_uses_gps("EKF3 IMU1 is using GPS")
    assert not ardupilot.ekf_uses_gps("EKF3 IMU0 origin set")
    assert ardupilot.ready_to_arm(False, True, True) is True
    assert ardupilot.ready_to_arm(False, True, False) is False    # pre-arm bit on at 24 s, GPS fused at 41 s
    assert ardupilot.ready_to_arm(True, False, False) is None     # PX4: not this way


def test_arducopter_boot_console_text_is_not_bad_input_but_other_bad_data_is():
    for text in (b"\n\nInit ArduCopte", b"Init Gyro", b"*", b"\n", b"AP_Logger_File: "):   # measured on SERIAL0
        assert ardupilot.console_text(text, is_px4=False, heard_heartbeat=True)
        assert ardupilot.console_text(text, is_px4=True, heard_heartbeat=False)   # before its first heartbeat
    assert not ardupilot.console_text(b"Init", is_px4=True, heard_heartbeat=True)    # PX4 prints none
    assert not ardupilot.console_text(b"\xfd\x09\x00", is_px4=False, heard_heartbeat=True)
    assert not ardupilot.console_text(b"", is_px4=False, heard_heartbeat=True)
