"""The fault table's judging where PX4 and the built-in sim differ (tools/cli/chaos): how still a held
vehicle is, how late the offboard-loss failsafe may be seen, which rows each flight controller has."""
from __future__ import annotations

from aeroperception.schemas import Vector3, VehicleState
from aeroperception.services.lib.geofence import Geofence
from aeroperception.tools.cli.chaos import build_rows, judge_safety
from aeroperception.tools.cli.chaos.judging import still_mps
from aeroperception.tools.cli.chaos.rows import FAILSAFE_SEEN_S, OFFBOARD_LOSS_S
from aeroperception.tools.harness import profile_services
from aeroperception.tools.harness.px4_stack import PX4_FLIGHT_SERVICES


def hovering(speed_mps: float, z: float = 5.0) -> list[tuple[float, VehicleState]]:
    return [(0.0, VehicleState(position_m=Vector3(z=z), velocity_mps=Vector3(x=speed_mps), armed=True,
                               flight_mode="OFFBOARD"))]


def test_a_px4_hold_wandering_with_its_gnss_estimate_is_still_where_the_sims_would_be_moving():
    # PX4 SIH's OFFBOARD hold measured up to 0.52 m/s (truth); the sim holds within ~0.1 m
    px4_ok, px4_why = judge_safety(hovering(0.5), [], Geofence.from_params(), "HOLDING", still_mps("px4"))
    sim_ok, sim_why = judge_safety(hovering(0.5), [], Geofence.from_params(), "HOLDING", still_mps("sim"))
    assert px4_ok and px4_why.startswith("holding"), px4_why
    assert not sim_ok and "ends moving at 0.5 m/s" in sim_why
    assert not judge_safety(hovering(1.5), [], Geofence.from_params(), "HOLDING", still_mps("px4"))[0]   # flying on


def test_the_offboard_loss_failsafe_may_be_seen_one_heartbeat_later_on_px4():
    assert FAILSAFE_SEEN_S["sim"] == OFFBOARD_LOSS_S + 0.5            # the sim's truth carries its mode at once
    assert FAILSAFE_SEEN_S["px4"] == OFFBOARD_LOSS_S + 1.0 + 0.5      # PX4's mode: HEARTBEAT, 1 Hz
    px4 = build_rows(PX4_FLIGHT_SERVICES, "px4")
    assert "2.5 s" in px4["hang_fmu"].expected and "2.5 s" in px4["failsafe_rtl"].expected
    assert "1.5 s" in build_rows(profile_services("sim"))["hang_fmu"].expected


def test_each_flight_controller_gets_the_rows_it_can_answer():
    px4 = build_rows(PX4_FLIGHT_SERVICES, "px4")
    sim = build_rows(profile_services("sim"))
    assert {"pilot_hold", "failsafe_rtl", "gps_failure"} <= set(px4) and not {"clock_jump", "fc_reboot"} & set(px4)
    assert {"clock_jump", "fc_reboot"} <= set(sim) and not {"pilot_hold", "gps_failure"} & set(sim)
    assert "SIM_GPS_USED 0" in px4["gps_failure"].injected       # SIH has no `failure gps off`


def test_a_hold_where_the_fc_says_it_is_moves_nothing_even_with_its_estimate_wandered_off():
    """PX4 on the ground after losing GPS: its estimate drifted 57 m off and 2 m into the ground; a
    hold at that estimate commands no motion. The same point anywhere else is outside the fence."""
    from pymavlink.dialects.v20 import common as mavlink

    from aeroperception.tools.harness import setpoint_problem
    mask = 0b0000_1100_0000_0000 | 0b0001_1100_0000   # position + velocity; no acceleration, yaw, yaw rate
    sp = mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask,
                                                                -54.8, 18.6, 2.0, 0, 0, 0, 0, 0, 0, 0, 0)
    fence = Geofence.from_params()
    assert "outside the fence" in setpoint_problem(sp, fence, -2.0 + 0.5)
    assert setpoint_problem(sp, fence, -2.0 + 0.5, here_enu_m=[18.5, -54.6, -2.1]) is None
    assert "outside the fence" in setpoint_problem(sp, fence, -2.0 + 0.5, here_enu_m=[10.0, 0.0, 5.0])
    assert setpoint_problem(sp, fence, -2.0 + 0.5, here_enu_m=[10.0, 0.0, 5.0], armed=False) is None
