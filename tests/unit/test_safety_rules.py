"""Safety's rule table entry by entry, and the aggregation that turns inputs into Facts
(plain objects, no Zenoh)."""
from __future__ import annotations

import pytest

from aeroperception.schemas import (
    BatteryState, DiagnosticStatus, GcsLink, LandedState, PerceptionHealth, SafetyStatus, Vector3, VehicleState,
    VehicleStatus,
)
from aeroperception.services.runtime import ParamSet
from aeroperception.services.runtime.config import build, check_covers
from aeroperception.services.safety import contract
from aeroperception.services.lib.geofence import Geofence, GeofenceError
from aeroperception.services.safety.monitor import Config, SafetyConfig, SafetyMonitor, classify_battery, parse_services
from aeroperception.services.safety.rules import (
    RULE_NAMES, RULES, Battery, Facts, GeofenceAction, evaluate,
)

S = SafetyStatus
NOMINAL = Facts()   # airborne False, everything fine
GROUND_WARN = (S.LEVEL_WARNING, S.ACTION_WARN)

# (rule, facts that trigger it (besides the airborne flag), airborne (level, action), ground (level, action))
ROWS = [
    ("emergency_stop", dict(estop="emergency stop executed (test)"),
     (S.LEVEL_EMERGENCY, S.ACTION_EMERGENCY_STOP), (S.LEVEL_EMERGENCY, S.ACTION_EMERGENCY_STOP)),
    ("fc_link_lost", dict(fc_connected=False), (S.LEVEL_EMERGENCY, S.ACTION_NONE), GROUND_WARN),
    ("fmu_down", dict(fmu_down="fmu not alive"), (S.LEVEL_EMERGENCY, S.ACTION_NONE), GROUND_WARN),
    ("battery_emergency", dict(battery=Battery.EMERGENCY, battery_remaining=0.05),
     (S.LEVEL_EMERGENCY, S.ACTION_LAND), GROUND_WARN),
    ("geofence_land", dict(geofence_status=S.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0,
                           geofence_action=GeofenceAction.LAND), (S.LEVEL_EMERGENCY, S.ACTION_LAND), GROUND_WARN),
    ("battery_critical", dict(battery=Battery.CRITICAL, battery_remaining=0.12),
     (S.LEVEL_CAUTION, S.ACTION_RTH), GROUND_WARN),
    ("geofence_return", dict(geofence_status=S.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0,
                             geofence_action=GeofenceAction.RETURN), (S.LEVEL_CAUTION, S.ACTION_RTH), GROUND_WARN),
    ("service_down", dict(services_down=("planner not alive",)), (S.LEVEL_CAUTION, S.ACTION_HOLD), GROUND_WARN),
    ("geofence_hold", dict(geofence_status=S.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0,
                           geofence_action=GeofenceAction.HOLD), (S.LEVEL_CAUTION, S.ACTION_HOLD), GROUND_WARN),
    ("geofence_warn", dict(geofence_status=S.GEOFENCE_VIOLATION, distance_to_geofence_m=-2.0,
                           geofence_action=GeofenceAction.WARN), GROUND_WARN, GROUND_WARN),
    ("battery_low", dict(battery=Battery.LOW, battery_remaining=0.25), GROUND_WARN, GROUND_WARN),
    ("geofence_near", dict(geofence_status=S.GEOFENCE_WARNING, distance_to_geofence_m=3.0), GROUND_WARN, GROUND_WARN),
    ("gcs_lost", dict(gcs_lost=True), GROUND_WARN, GROUND_WARN),
    ("perception_unhealthy", dict(perception_problem="perception not healthy (VIO FAILED)"), GROUND_WARN, GROUND_WARN),
    ("fc_failsafe", dict(fc_failsafe="RTL"), GROUND_WARN, GROUND_WARN),
    ("battery_unknown", dict(battery=Battery.UNKNOWN), GROUND_WARN, GROUND_WARN),
]


def test_every_rule_row_has_a_test_row_in_table_order():
    assert [r[0] for r in ROWS] == RULE_NAMES


def test_nominal_facts_match_no_rule():
    for airborne in (False, True):
        v = evaluate(Facts(airborne=airborne))
        assert (v.level, v.action, v.rules, v.warnings, v.errors) == (S.LEVEL_NOMINAL, S.ACTION_NONE, (), (), ())


@pytest.mark.parametrize("name,facts,air,ground", ROWS, ids=[r[0] for r in ROWS])
def test_rule_row_alone_decides_level_and_action(name, facts, air, ground):
    for airborne, expected in ((True, air), (False, ground)):
        v = evaluate(Facts(airborne=airborne, **facts))
        assert v.rules == (name,), v
        assert (v.level, v.action) == expected
        messages = v.errors if expected[0] >= S.LEVEL_CAUTION else v.warnings
        assert len(messages) == 1 and messages[0] and not (v.errors and v.warnings)


@pytest.mark.parametrize("name,facts,air,ground", ROWS, ids=[r[0] for r in ROWS])
def test_no_motion_is_recommended_on_the_ground(name, facts, air, ground):
    assert ground[1] not in (S.ACTION_HOLD, S.ACTION_RTH, S.ACTION_LAND)


def test_geofence_breach_with_action_none_is_reported_but_recommends_nothing():
    v = evaluate(Facts(airborne=True, geofence_status=S.GEOFENCE_VIOLATION, distance_to_geofence_m=-1.0,
                       geofence_action=GeofenceAction.NONE))
    assert (v.level, v.action, v.rules) == (S.LEVEL_NOMINAL, S.ACTION_NONE, ())


def test_first_matching_row_wins_and_every_match_reports():
    v = evaluate(Facts(airborne=True, battery=Battery.CRITICAL, battery_remaining=0.1,
                       services_down=("planner not alive",), gcs_lost=True))
    assert (v.level, v.action) == (S.LEVEL_CAUTION, S.ACTION_RTH)   # the FC flies RTL without the planner
    assert v.rules == ("battery_critical", "service_down", "gcs_lost")
    assert v.errors == ("battery critical -> RTH", "planner not alive -> HOLD")
    assert v.warnings == ("ground station link lost",)


def test_lost_fc_link_outranks_motion_rows_nothing_can_reach_the_vehicle():
    v = evaluate(Facts(airborne=True, fc_connected=False, battery=Battery.EMERGENCY, battery_remaining=0.03))
    assert (v.level, v.action) == (S.LEVEL_EMERGENCY, S.ACTION_NONE)
    assert "its own failsafe" in v.errors[0]


def test_messages_say_why_the_fc_takes_over_only_in_the_air():
    air = evaluate(Facts(airborne=True, fmu_down="fmu not alive"))
    ground = evaluate(Facts(airborne=False, fmu_down="fmu not alive"))
    assert air.errors == ("fmu not alive: the flight controller's offboard-loss failsafe takes over",)
    assert ground.warnings == ("fmu not alive",)
    assert evaluate(Facts(fc_connected=False, fc_ever_connected=False)).warnings == ("no flight controller link yet",)


def test_rules_are_ordered_most_severe_first_by_airborne_level():
    levels = [r.airborne[0] for r in RULES]
    assert levels == sorted(levels, reverse=True)


# ------------------------------------------------------------------ aggregation

def state(armed=True, landed=LandedState.IN_AIR, xyz=(0.0, 0.0, 5.0), connected=True, battery=None):
    return VehicleState(armed=armed, landed_state=landed, position_m=Vector3(x=xyz[0], y=xyz[1], z=xyz[2]),
                        connected=connected, battery_remaining=battery, battery_voltage_v=15.2 if battery else None)


def refresh_diagnostics(m: SafetyMonitor, now: float) -> None:
    for name in m.cfg.required_services:
        m.on_diagnostics(DiagnosticStatus(name=name, level=DiagnosticStatus.OK), now)


def healthy_monitor(now=0.0, **cfg) -> SafetyMonitor:
    m = SafetyMonitor(build(Config, contract.PARAMS, **cfg))
    for name in m.cfg.required_services:
        m.on_liveliness(name, True, now)
        m.on_diagnostics(DiagnosticStatus(name=name, level=DiagnosticStatus.OK), now)
    m.on_vehicle_state(state(battery=0.9), now)
    m.on_battery(BatteryState(voltage_v=15.8, remaining_fraction=0.9), now)
    return m


def test_healthy_inputs_give_a_nominal_status_with_every_field_filled():
    m = healthy_monitor()
    s = m.status(0.1, stamp_ns=123)
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_NOMINAL, S.ACTION_NONE)
    assert (s.heartbeats_alive, s.heartbeats_total, s.dead_heartbeats) == (3, 3, [])
    assert s.px4_connected and s.estimator_healthy and s.controller_healthy and s.trajectory_healthy
    assert not s.gcs_connected   # no gcs/link heard: not connected, but not "lost" either
    assert (s.battery_remaining, s.battery_voltage_v, s.battery_status) == (0.9, 15.8, S.BATTERY_OK)
    assert s.geofence_status == S.GEOFENCE_OK and s.distance_to_geofence_m == pytest.approx(115.0)
    assert (s.active_warnings, s.active_errors, s.header.stamp_ns) == ([], [], 123)


def test_a_dead_required_service_is_listed_and_held_for_in_the_air_then_recovers():
    m = healthy_monitor()
    m.on_liveliness("planner", False, 1.0)
    m.on_vehicle_state(state(battery=0.9), 1.0)
    s = m.status(1.0)
    assert s.dead_heartbeats == ["planner"] and (s.heartbeats_alive, s.heartbeats_total) == (2, 3)
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_CAUTION, S.ACTION_HOLD)
    assert not s.trajectory_healthy and s.active_errors == ["planner not alive -> HOLD"]
    m.on_liveliness("planner", True, 2.0)      # restarted: a grace period to report diagnostics
    s = m.status(2.1)
    assert (s.dead_heartbeats, s.recommended_action) == ([], S.ACTION_NONE)


def test_a_hung_service_counts_as_a_dead_heartbeat_and_an_error_report_as_unhealthy():
    m = healthy_monitor(diagnostics_timeout_s=3.0)
    for t in (1.0, 2.0, 3.0):
        m.on_diagnostics(DiagnosticStatus(name="fmu", level=DiagnosticStatus.OK), t)
        m.on_diagnostics(DiagnosticStatus(name="mission", level=DiagnosticStatus.OK), t)
        m.on_vehicle_state(state(battery=0.9), t)
    m.on_battery(BatteryState(voltage_v=15.8, remaining_fraction=0.9), 3.0)
    s = m.status(3.5)   # planner's last diagnostics at 0.0
    assert s.dead_heartbeats == ["planner"] and s.active_errors == ["planner hung: no diagnostics for over 3 s -> HOLD"]
    m.on_diagnostics(DiagnosticStatus(name="planner", level=DiagnosticStatus.ERROR, message="no fresh state"), 3.5)
    s = m.status(3.5)
    assert s.dead_heartbeats == [] and s.active_errors == ["planner reports ERROR: no fresh state -> HOLD"]
    # A restart forgets the old process's ERROR.
    m.on_liveliness("planner", False, 3.6)
    m.on_liveliness("planner", True, 3.7)
    assert m.service_problem("planner", 3.8) == ("", "")


def test_fc_link_lost_when_state_is_stale_or_not_connected():
    m = healthy_monitor(state_timeout_s=0.5)
    assert m.status(0.4).px4_connected
    s = m.status(0.6)
    assert not s.px4_connected and not s.estimator_healthy and not s.controller_healthy
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_EMERGENCY, S.ACTION_NONE)  # last known: airborne
    m.on_vehicle_state(state(connected=False, battery=0.9), 0.7)
    assert m.status(0.7).safety_level == S.LEVEL_EMERGENCY
    m.on_vehicle_state(state(armed=False, landed=LandedState.ON_GROUND, connected=False), 0.8)
    assert (m.status(0.8).safety_level, m.status(0.8).recommended_action) == GROUND_WARN


@pytest.mark.parametrize("remaining,expected", [
    (0.31, Battery.OK), (0.29, Battery.LOW), (0.14, Battery.CRITICAL), (0.06, Battery.EMERGENCY),
    (None, Battery.UNKNOWN), (float("nan"), Battery.UNKNOWN)])
def test_battery_thresholds(remaining, expected):
    assert classify_battery(remaining, BatteryState.WARNING_NONE, build(Config, contract.PARAMS)) == expected


def test_battery_class_is_the_worse_of_ours_and_the_flight_controllers_warning():
    cfg = build(Config, contract.PARAMS)
    assert classify_battery(0.9, BatteryState.WARNING_CRITICAL, cfg) == Battery.CRITICAL
    assert classify_battery(0.05, BatteryState.WARNING_LOW, cfg) == Battery.EMERGENCY
    assert classify_battery(None, BatteryState.WARNING_EMERGENCY, cfg) == Battery.EMERGENCY


def test_battery_from_battery_status_then_state_vehicle_when_it_goes_stale():
    m = healthy_monitor(battery_timeout_s=5.0)
    m.on_battery(BatteryState(voltage_v=14.0, remaining_fraction=0.12), 1.0)
    m.on_vehicle_state(state(battery=0.9), 1.0)
    s = m.status(1.0)
    assert (s.battery_remaining, s.battery_status, s.recommended_action) == (0.12, S.BATTERY_CRITICAL, S.ACTION_RTH)
    refresh_diagnostics(m, 7.0)
    m.on_vehicle_state(state(battery=0.05), 7.0)
    s = m.status(7.0)
    assert (s.battery_remaining, s.battery_status, s.recommended_action) == (0.05, S.BATTERY_CRITICAL, S.ACTION_LAND)


def test_geofence_distance_and_status_follow_the_position():
    m = healthy_monitor(geofence=Geofence.from_params(radius_m=20.0, max_altitude_m=30.0), geofence_warning_margin_m=5.0)
    for xyz, status, dist in (((0, 0, 5), S.GEOFENCE_OK, 20.0), ((17, 0, 5), S.GEOFENCE_WARNING, 3.0),
                              ((0, 22, 5), S.GEOFENCE_VIOLATION, -2.0), ((0, 0, 31), S.GEOFENCE_VIOLATION, -1.0)):
        m.on_vehicle_state(state(xyz=xyz, battery=0.9), 0.1)
        s = m.status(0.1)
        assert (s.geofence_status, s.distance_to_geofence_m) == (status, pytest.approx(dist))
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_CAUTION, S.ACTION_HOLD)  # default geofence_action 2


def test_a_non_finite_position_leaves_the_geofence_unknown():
    m = healthy_monitor()
    m.on_vehicle_state(state(xyz=(float("nan"), 0.0, 5.0), battery=0.9), 0.1)
    s = m.status(0.1)
    assert (s.geofence_status, s.distance_to_geofence_m) == (S.GEOFENCE_OK, None)


def test_gcs_lost_only_after_it_was_heard_and_perception_unknown_until_heard():
    m = healthy_monitor(gcs_timeout_s=3.5, perception_timeout_s=3.0)
    assert not m.facts(0.1).gcs_lost and m.facts(0.1).perception_problem == ""
    m.on_gcs_link(GcsLink(connected=True), 0.2)
    assert m.status(0.2).gcs_connected
    m.on_gcs_link(GcsLink(connected=False), 0.3)
    assert m.facts(0.3).gcs_lost
    m.on_gcs_link(GcsLink(connected=True), 0.4)
    assert m.facts(4.0).gcs_lost   # gcs/link silent: not connected any more
    m.on_perception(PerceptionHealth(vio_status=PerceptionHealth.FAILED, overall_healthy=False), 0.5)
    assert m.facts(0.5).perception_problem == "perception not healthy (VIO FAILED)"
    m.on_perception(PerceptionHealth(vio_status=PerceptionHealth.HEALTHY, overall_healthy=True), 0.6)
    assert m.facts(0.6).perception_problem == ""
    assert m.facts(4.0).perception_problem == "perception/health silent for over 3 s"


def test_fc_failsafe_is_reported():
    m = healthy_monitor()
    m.on_vehicle_status(VehicleStatus(nav_state="RTL", failsafe=True, armed=True), 0.1)
    assert m.facts(0.1).fc_failsafe == "RTL"


def test_emergency_stop_latches_until_the_vehicle_is_armed_again():
    m = healthy_monitor()
    m.on_emergency_stop("operator: fire", True, "confirmed by heartbeat")
    s = m.status(0.1)
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_EMERGENCY, S.ACTION_EMERGENCY_STOP)
    assert s.active_errors[0] == "emergency stop executed (operator: fire)"
    m.on_vehicle_state(state(armed=True), 0.2)            # still armed: stays
    m.on_vehicle_state(state(armed=False, landed=LandedState.ON_GROUND), 0.3)
    assert m.status(0.3).recommended_action == S.ACTION_EMERGENCY_STOP   # disarmed afterwards: still shown
    m.on_vehicle_state(state(armed=True, landed=LandedState.ON_GROUND, battery=0.9), 0.4)
    assert m.status(0.4).recommended_action == S.ACTION_NONE


def test_required_services_parsing_and_params_build_a_config():
    assert parse_services(" fmu, planner,,mission ,fmu") == ("fmu", "planner", "mission")
    ps = ParamSet.from_declarations(contract.PARAMS)
    cfg = build(Config, ps)
    assert cfg.required_services == ("fmu", "planner", "mission")
    assert (cfg.battery_warn_fraction, cfg.battery_critical_fraction, cfg.battery_emergency_fraction) == (0.30, 0.15, 0.07)
    assert cfg.geofence_action == GeofenceAction.HOLD and cfg.geofence.radius_m == 500.0
    with pytest.raises(Exception, match="not one of"):
        ps.set("geofence_action", 4)   # terminate is not offered


def test_the_service_config_references_every_parameter_and_a_bad_polygon_is_refused():
    check_covers(SafetyConfig, contract.PARAMS, "safety")
    ps = ParamSet.from_declarations(contract.PARAMS)
    ps.set("geofence_polygon", "0,0;10,0")
    with pytest.raises(GeofenceError, match="at least 3"):
        build(SafetyConfig, ps)
