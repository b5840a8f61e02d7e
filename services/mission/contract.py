"""Contract of the mission service: keys in/out and parameters."""
from aeroperception.schemas import (
    ArmReply, ArmRequest, Empty, GcsLink, GetMissionReply, LoadMissionReply, LoadMissionRequest,
    MissionCommand, MissionGoal, MissionStatus, OccupancyGrid, ParamList, PerceptionHealth, Reply, SafetyStatus,
    SetModeReply, SetModeRequest, Trajectory, TrajectoryStatus, UAVStatus, VehicleState, WaypointReached,
)
from aeroperception.services.lib.geofence import GEOFENCE_PARAMS
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics

NAME = "mission"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState),
    Topic("perception/health", PerceptionHealth),
    Topic("mission/command", MissionCommand, note="fire-and-forget operator command", strict=True),
    Topic("safety/status", SafetyStatus, note="a rising recommended_action HOLD/RTH/LAND acts once"),
    Topic("planner/status", TrajectoryStatus, note="obstacle_state blocked/unreachable -> blocked_action; its trajectory "
                                                   "ABORTED (refused) -> hold; the planner's parts for UAVStatus"),
    Topic("perception/costmap", OccupancyGrid, note="a loaded waypoint inside an obstacle is warned about"),
    Topic("gcs/link", GcsLink, note="a ground station once heard going down -> hold"),
)
# fmu's or the planner's token gone = an outage -> HOLDING until it is back and re-checked.
LIVELINESS = ("fmu", "planner")
OUTPUTS = Topics(
    Topic("mission/status", MissionStatus, 2.0, note="FSM state, current waypoint, distance to goal (status_rate_hz)"),
    Topic("mission/active_goal", MissionGoal, 2.0, note='also at once on a change; frame_id "hold" = hold position'),
    Topic("mission/active_trajectory", Trajectory, 2.0,
          note="also at once with each goal: the waypoints ahead for the planner's generator; empty = none"),
    Topic("mission/waypoint_reached", WaypointReached, note="event: a mission waypoint reached"),
    Topic("mission/uav_status", UAVStatus, 2.0, note="UAVMode from the FSM and vehicle state, the planner's parts, "
                                                     "links, mission progress (status_rate_hz)"),
)
SERVICES = Queries(
    Query("mission/srv/load", LoadMissionRequest, LoadMissionReply),
    # the reply waits for fmu's answer (ARM, DISARM, TAKEOFF's arming): locked=False, it locks itself
    Query("mission/srv/command", MissionCommand, Reply, handler="on_command_request", locked=False),
    Query("mission/srv/get", Empty, GetMissionReply, note="the loaded mission (gcs serves it to downloads)"),
)
STATE_FILE = "mission.json"   # in state_dir: the loaded mission and its progress, for a restart
ACTIONS = ("mission/action/takeoff", "mission/action/land", "mission/action/goto", "mission/action/set_trajectory")
CALLS = Queries(
    Query("fmu/srv/arm", ArmRequest, ArmReply),
    Query("fmu/srv/set_mode", SetModeRequest, SetModeReply),
    Query("config/planner/@params", None, ParamList, note="every 3 s: the planner's live hover_speed_mps for UAVMode"),
)
PARAMS = [
    Param("takeoff_altitude_m", 3.0, "m", 0.5, 120.0, description="default takeoff altitude (MIS-1: 3 m)"),
    Param("altitude_tolerance_m", 0.3, "m", 0.05, 2.0, description="takeoff counts as done inside this"),
    Param("require_perception", False, description="gate EXECUTING on perception/health (missions may override)"),
    Param("perception_timeout_s", 3.0, "s", 0.5, 30.0, description="no perception/health this long = unhealthy"),
    Param("perception_recovery_s", 10.0, "s", 1.0, 120.0, description="hold this long for perception, then RTL"),
    Param("disarm_after_landing_s", 5.0, "s", 1.0, 60.0, description="disarm if the FC has not auto-disarmed by then"),
    Param("land_on_complete", True, description="land after the last waypoint (else hold)"),
    Param("bridge_timeout_s", 5.0, "s", 0.5, 30.0, description="timeout of fmu/srv/* calls"),
    Param("status_rate_hz", 2.0, "Hz", 0.5, 20.0, description="mission/status rate"),
    Param("vehicle_timeout_s", 0.5, "s", 0.1, 10.0, description="state/vehicle older than this = fmu outage: hold"),
    Param("resume_after_outage", False,
          description="after an fmu outage resume the mission by itself (default: hold until START)"),
    Param("restore_timeout_s", 5.0, "s", 0.5, 60.0,
          description="after a restart, wait this long for vehicle state before accepting commands"),
    Param("mission_file", "",
          description="mission file (JSON or YAML) loaded at start-up (unless a restart restores one "
                      "in flight) and when set live; '' = none (aero up --mission FILE sets it)"),
    Param("blocked_timeout_s", 5.0, "s", 0.5, 600.0,
          description="planner/status says the goal is blocked/unreachable this long -> blocked_action"),
    Param("blocked_action", "hold", choices=("hold", "skip", "rtl"),
          description="an unreachable goal: hold (HOLDING with the reason, wait for the operator), "
                      "skip (fly on to the next waypoint; a goto holds) or rtl"),
    Param("land_handoff_altitude_m", 1.0, "m", 0.3, 10.0,
          description="a landing at a target or with a descent rate is flown by the planner down to this "
                      "height above the landing point, then the flight controller lands"),
    Param("state_dir", "", start_only=True,
          description="where the loaded mission and progress persist; '' = $AERO_STATE_DIR or ~/.aero/state, /<vehicle>/"),
    # limits every mission, goto and takeoff is checked against (with the shared geofence)
    Param("max_takeoff_altitude_m", 50.0, "m", 1.0, 10_000.0,
          description="highest takeoff altitude accepted (also capped by geofence_max_altitude_m)"),
    Param("min_acceptance_radius_m", 0.1, "m", 0.01, 100.0, description="smallest waypoint acceptance radius accepted"),
    Param("max_acceptance_radius_m", 10.0, "m", 0.1, 1000.0, description="largest waypoint acceptance radius accepted"),
    *GEOFENCE_PARAMS,
]
