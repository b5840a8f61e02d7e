"""Contract of the safety service: keys in/out and parameters (defaults PX4-like, units named)."""
from aeroperception.schemas import (
    BatteryState, DiagnosticStatus, EmergencyStopReply, EmergencyStopRequest, GcsLink, PerceptionHealth,
    SafetyStatus, VehicleState, VehicleStatus,
)
from aeroperception.services.lib.geofence import GEOFENCE_PARAMS
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics

NAME = "safety"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState, note="FC link (connected + freshness), armed/in air, position, battery"),
    Topic("fmu/out/battery_status", BatteryState, note="battery (preferred over state/vehicle's copy)"),
    Topic("fmu/out/vehicle_status", VehicleStatus, note="the FC's own failsafe flag and mode (reported)"),
    Topic("gcs/link", GcsLink, note="ground station heard or lost"),
    Topic("perception/health", PerceptionHealth, note="optional: unknown while absent"),
    Topic("diagnostics/*", DiagnosticStatus, note="a required service reporting ERROR is unhealthy"),
)
OUTPUTS = Topics(
    Topic("safety/status", SafetyStatus, 1.0, note="and at once on a change of level/action/rules"),
)
LIVELINESS = ("*",)     # the required services (required_services) must be alive
SERVICES = Queries(
    # locked=False: the handler waits for the FC's outcome (fmu/srv/emergency_stop) and locks itself
    Query("safety/srv/emergency_stop", EmergencyStopRequest, EmergencyStopReply, locked=False),
)
CALLS = Queries(
    Query("fmu/srv/emergency_stop", EmergencyStopRequest, EmergencyStopReply, note="FC flight termination"),
)
# PX4's GF_ACTION values; 4 (terminate) is deliberately not offered: a multirotor falls. The only
# way to stop the motors is an operator's safety/srv/emergency_stop.
GEOFENCE_ACTIONS = {0: "none", 1: "warn", 2: "hold", 3: "return", 5: "land"}
PARAMS = [
    Param("required_services", "fmu,planner,mission",
          description="comma list of services whose liveliness (and health) the vehicle needs"),
    Param("battery_warn_fraction", 0.30, "", 0.0, 1.0, description="below: WARN (PX4 BAT_LOW_THR is 0.15)"),
    Param("battery_critical_fraction", 0.15, "", 0.0, 1.0,
          description="below: return home (RTH); PX4 BAT_CRIT_THR is 0.07"),
    Param("battery_emergency_fraction", 0.07, "", 0.0, 1.0,
          description="below: LAND where it is; PX4 BAT_EMERGEN_THR is 0.05"),
    *GEOFENCE_PARAMS,
    Param("geofence_warning_margin_m", 5.0, "m", 0.0, 1000.0, description="closer to the boundary: WARN"),
    Param("geofence_action", 2, "", choices=tuple(GEOFENCE_ACTIONS),
          description="on a breach (PX4 GF_ACTION, same default): 0 none, 1 warn, 2 hold, 3 return, 5 land"),
    Param("state_timeout_s", 0.5, "s", 0.1, 10.0, description="older state/vehicle: FC link lost"),
    Param("battery_timeout_s", 5.0, "s", 1.0, 60.0, description="older fmu/out/battery_status: use state/vehicle's"),
    Param("gcs_timeout_s", 3.5, "s", 0.5, 60.0, description="gcs/link silent this long: ground station unknown"),
    Param("perception_timeout_s", 3.0, "s", 0.5, 60.0, description="perception/health silent this long: unhealthy"),
    Param("diagnostics_timeout_s", 3.0, "s", 1.0, 60.0,
          description="a required service alive but without diagnostics this long counts as dead (hung)"),
    Param("estop_timeout_s", 4.0, "s", 0.5, 20.0, description="wait this long for fmu/srv/emergency_stop"),
    Param("check_rate_hz", 10.0, "Hz", 1.0, 50.0, description="rule evaluation rate (changes publish at once)"),
    Param("status_rate_hz", 1.0, "Hz", 0.2, 10.0, description="safety/status rate when nothing changes"),
]
