"""UAVStatus / UAVMode from the mission FSM, the vehicle's state and the planner's status."""
from __future__ import annotations

import pytest
from types import SimpleNamespace

from aeroperception.schemas import LandedState, SafetyStatus, TrajectoryStatus, UAVMode, Vector3, VehicleState
from aeroperception.services.mission.fsm import State
from aeroperception.services.mission.uav_status import GcsLinkWatch, UavStatusBuilder, mission_progress_pct, uav_mode


def vehicle(speed=0.0, armed=True, landed=LandedState.IN_AIR, mode="OFFBOARD") -> VehicleState:
    return VehicleState(velocity_mps=Vector3(x=speed), armed=armed, landed_state=landed, flight_mode=mode,
                        connected=True, battery_remaining=0.8)


GROUND = dict(armed=False, landed=LandedState.ON_GROUND, mode="HOLD")


@pytest.mark.parametrize("fsm, v, flew, expected", [
    (State.IDLE, None, False, UAVMode.STATE_IDLE),
    (State.IDLE, vehicle(**GROUND), False, UAVMode.STATE_IDLE),
    (State.IDLE, vehicle(**GROUND), True, UAVMode.STATE_LANDED),
    (State.IDLE, vehicle(landed=LandedState.ON_GROUND), False, UAVMode.STATE_ARMED),
    (State.TAKEOFF, vehicle(1.0), False, UAVMode.STATE_TAKING_OFF),
    (State.EXECUTING, vehicle(1.5), True, UAVMode.STATE_FLYING),
    (State.EXECUTING, vehicle(0.1), True, UAVMode.STATE_HOVERING),    # waiting at a waypoint is hovering
    (State.HOLDING, vehicle(0.05), True, UAVMode.STATE_HOVERING),
    (State.HOLDING, vehicle(0.8), True, UAVMode.STATE_FLYING),        # braking into the hold
    (State.LAND, vehicle(0.5), True, UAVMode.STATE_LANDING),
])
def test_state_from_the_fsm_and_the_vehicle(fsm, v, flew, expected):
    assert uav_mode(fsm, v, None, None, flew).state == expected


def test_a_safety_emergency_wins_and_control_mode_follows_the_fc_and_the_planner():
    emergency = SafetyStatus(safety_level=SafetyStatus.LEVEL_EMERGENCY)
    assert uav_mode(State.EXECUTING, vehicle(2.0), emergency, None, True).state == UAVMode.STATE_EMERGENCY
    flying = TrajectoryStatus(status=TrajectoryStatus.STATUS_EXECUTING, trajectory_id="survey_01@0",
                              active_controller="feedforward")
    goal_by_goal = TrajectoryStatus(status=TrajectoryStatus.STATUS_EXECUTING, trajectory_id="goal-3",
                                    active_controller="feedforward")
    assert uav_mode(State.EXECUTING, vehicle(2.0), None, flying, True).control_mode == UAVMode.MODE_TRAJECTORY
    assert uav_mode(State.EXECUTING, vehicle(2.0), None, goal_by_goal, True).control_mode == UAVMode.MODE_OFFBOARD
    velocity = TrajectoryStatus(trajectory_id="goal-3", active_controller="velocity")
    assert uav_mode(State.EXECUTING, vehicle(2.0), None, velocity, True).control_mode == UAVMode.MODE_VELOCITY
    assert uav_mode(State.HOLDING, vehicle(mode="POSCTL"), None, None, True).control_mode == UAVMode.MODE_POSITION
    assert uav_mode(State.HOLDING, vehicle(mode="STABILIZED"), None, None, True).control_mode == UAVMode.MODE_MANUAL
    rtl = uav_mode(State.LAND, vehicle(mode="RTL"), None, None, True)
    assert rtl.submode == "rth" and rtl.can_land is False and rtl.armed


def test_what_may_be_asked_now():
    idle = uav_mode(State.IDLE, vehicle(**GROUND), None, None, False)
    assert idle.can_arm and idle.can_takeoff and not idle.can_land and idle.submode == "idle"
    air = uav_mode(State.HOLDING, vehicle(), None, None, True)
    assert not air.can_arm and not air.can_takeoff and air.can_land
    lost = vehicle(**GROUND)
    lost.connected = False
    assert not uav_mode(State.IDLE, lost, None, None, False).can_takeoff


def test_the_status_carries_the_planners_parts_links_and_progress_and_remembers_a_flight():
    b = UavStatusBuilder("uav1")
    parts = TrajectoryStatus(active_trajectory_generator="smooth", active_controller="velocity", active_estimator="vio")
    st = b.build(State.EXECUTING, vehicle(1.0), None, parts, True, "survey_01", 50.0)
    assert (st.uav_id, st.active_trajectory_generator, st.active_controller, st.active_estimator) == \
        ("uav1", "smooth", "velocity", "vio")
    assert st.px4_connected and st.gcs_connected and st.battery_remaining == 0.8
    assert st.current_mission_id == "survey_01" and st.mission_progress_percent == 50.0
    assert 0.0 <= st.memory_percent <= 100.0 and st.cpu_percent >= 0.0
    landed = b.build(State.IDLE, vehicle(**GROUND), None, None, False, "", 0.0)
    assert landed.current_mode.state == UAVMode.STATE_LANDED and landed.active_controller == ""


def test_hovering_is_judged_by_the_planners_live_hover_speed_and_the_fc_latency_is_its_states_age():
    b = UavStatusBuilder("uav")
    slow = vehicle(0.4)
    assert b.build(State.HOLDING, slow, None, None, False, "", 0.0).current_mode.state == UAVMode.STATE_FLYING
    b.heard_planner_params({"hover_speed_mps": 0.5, "kp": 0.8})     # config/planner/@params
    assert b.build(State.HOLDING, slow, None, None, False, "", 0.0).current_mode.state == UAVMode.STATE_HOVERING
    b.heard_planner_params({"hover_speed_mps": "fast"})              # not a speed: the last one stays
    assert b.hover_speed_mps == 0.5
    assert b.build(State.IDLE, None, None, None, False, "", 0.0).px4_latency_s is None
    for age in (0.004, 0.006, 0.5, 0.005, -0.001):                   # a late one does not make the figure
        b.heard_vehicle(age)
    assert b.build(State.IDLE, slow, None, None, False, "", 0.0).px4_latency_s == pytest.approx(0.005)


def test_progress_counts_waypoints_passed_and_is_zero_idle_or_without_a_mission():
    m = SimpleNamespace(waypoints=[1, 2, 3, 4])
    assert mission_progress_pct(State.EXECUTING, m, 1) == 25.0
    assert mission_progress_pct(State.EXECUTING, m, -1) == 0.0 and mission_progress_pct(State.LAND, m, 9) == 100.0
    assert mission_progress_pct(State.IDLE, m, 2) == 0.0 and mission_progress_pct(State.EXECUTING, None, 2) == 0.0


def test_only_a_change_of_a_ground_link_once_seen_is_an_event():
    w = GcsLinkWatch()
    assert w.up is None and w.heard(False) is None         # never up: flying without a ground station
    assert w.heard(True) is True and w.heard(True) is None  # repeats at 1 Hz: no event
    assert w.heard(False) is False and w.up is False
