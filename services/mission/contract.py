"""Contract of the mission service: keys in/out and parameters."""
from aeroperception.schemas import (
    ArmReply, ArmRequest, Empty, GetMissionReply, LoadMissionReply, LoadMissionRequest, MissionCommand,
    MissionStatus, PerceptionHealth, PoseStamped, Reply, SetModeReply, SetModeRequest, VehicleState,
    WaypointReached,
)
from aeroperception.services.runtime import Param

NAME = "mission"
INPUTS = {
    "state/vehicle": VehicleState,
    "perception/health": PerceptionHealth,
    "mission/command": MissionCommand,      # fire-and-forget operator command
}
OUTPUTS = {
    "mission/status": MissionStatus,        # 2 Hz
    "mission/active_goal": PoseStamped,     # on change; frame_id "hold" = hold position
    "mission/waypoint_reached": WaypointReached,
}
SERVICES = {                                # queryables served: request -> reply
    "mission/srv/load": (LoadMissionRequest, LoadMissionReply),
    "mission/srv/command": (MissionCommand, Reply),
    "mission/srv/get": (Empty, GetMissionReply),    # the loaded mission (gcs serves it to downloads)
}
ACTIONS = ["takeoff", "land", "goto"]       # mission/action/<name>/{goal,cancel,feedback,result}
CALLS = {                                   # queryables used (served by fmu)
    "fmu/srv/arm": (ArmRequest, ArmReply),
    "fmu/srv/set_mode": (SetModeRequest, SetModeReply),
}
PARAMS = [
    Param("takeoff_altitude_m", 3.0, "m", 0.5, 120.0, description="default takeoff altitude (seed: 3 m)"),
    Param("altitude_tolerance_m", 0.3, "m", 0.05, 2.0, description="takeoff counts as done inside this"),
    Param("require_perception", False, description="gate EXECUTING on perception/health (missions may override)"),
    Param("perception_timeout_s", 3.0, "s", 0.5, 30.0, description="no perception/health this long = unhealthy"),
    Param("perception_recovery_s", 10.0, "s", 1.0, 120.0, description="hold this long for perception, then RTL"),
    Param("disarm_after_landing_s", 5.0, "s", 1.0, 60.0, description="disarm if the FC has not auto-disarmed by then"),
    Param("land_on_complete", True, description="land after the last waypoint (else hold)"),
    Param("bridge_timeout_s", 5.0, "s", 0.5, 30.0, description="timeout of fmu/srv/* calls"),
    Param("status_rate_hz", 2.0, "Hz", 0.5, 20.0, description="mission/status rate"),
]
