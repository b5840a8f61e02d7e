"""AeroPerception message schemas: every message, service and action type, msgpack on the wire.

    from aeroperception.schemas import VehicleState, encode, decode

See README.md in this folder for the wire format and the map from every seed/ROS type to its schema.
"""
from ._base import (
    REGISTRY, Header, Message, NDArray, SchemaError, check_known_fields, decode, encode, from_builtins, get_schema,
    now_ns, schema, schema_id, to_builtins,
)
from .geometry import Pose, PoseStamped, Quaternion, Twist, Vector3
from .sensors import (
    BatteryState, CameraInfo, Detection2D, Detection2DArray, DiagnosticArray, DiagnosticStatus,
    Image, Imu, OccupancyGrid, Odometry, PerceptionHealth, PointCloud, VioHealth,
)
from .safety import SafetyStatus
from .vehicle import (
    Attitude, ControlOutput, EstimatorStatus, GpsPosition, HomePosition, LandedState, LocalPosition, TrajectorySetpoint, UAVMode,
    UAVStatus, VehicleState, VehicleStatus,
)
from .planning import CollisionConstraint, Trajectory, TrajectoryLimits, TrajectoryStatus
from .gcs import GcsLink, Joystick
from .objects import ObjectEvent, TrackedObject, TrackedObjectArray
from .mission import (
    Mission, MissionCommand, MissionGoal, MissionStatus, MissionTrajectory, Waypoint, WaypointReached, load_mission_file,
    parse_mission,
)
from .services import (
    ArmReply, ArmRequest, EmergencyStopReply, EmergencyStopRequest, Empty, GetMissionReply, LoadMissionReply,
    LoadMissionRequest, Reply, SelectPluginReply, SelectPluginRequest, SetModeReply, SetModeRequest,
    VioResetRequest,
)
from .actions import (
    ACTIONS, ActionFeedback, ActionResult, ActionSpec, CancelReply, CancelRequest,
    GoalReply, GoalStatus, GoToPositionFeedback, GoToPositionGoal, GoToPositionResult,
    LandFeedback, LandGoal, LandResult, ResultRequest, SetTrajectoryFeedback, SetTrajectoryGoal,
    SetTrajectoryResult, TakeoffFeedback, TakeoffGoal, TakeoffResult,
)

__all__ = [
    # machinery
    "Message", "NDArray", "Header", "SchemaError", "schema", "REGISTRY", "get_schema", "encode",
    "decode", "to_builtins", "from_builtins", "check_known_fields", "schema_id", "now_ns",
    # geometry
    "Vector3", "Quaternion", "Pose", "Twist", "PoseStamped",
    # sensors, perception, health
    "Imu", "Image", "CameraInfo", "PointCloud", "OccupancyGrid", "Detection2D", "Detection2DArray",
    "BatteryState", "DiagnosticStatus", "DiagnosticArray", "Odometry", "VioHealth", "PerceptionHealth",
    # vehicle
    "LandedState", "VehicleState", "TrajectorySetpoint", "ControlOutput", "UAVMode", "UAVStatus",
    "VehicleStatus", "LocalPosition", "Attitude", "HomePosition", "GpsPosition", "EstimatorStatus",
    # planning and mission
    "Trajectory", "TrajectoryLimits", "TrajectoryStatus", "CollisionConstraint", "Waypoint", "Mission", "parse_mission",
    "load_mission_file", "MissionStatus", "MissionTrajectory", "MissionCommand", "MissionGoal", "WaypointReached",
    # ground station link
    "GcsLink", "Joystick",
    # tracked objects
    "TrackedObject", "TrackedObjectArray", "ObjectEvent",
    # safety
    "SafetyStatus",
    # services
    "Empty", "Reply", "ArmRequest", "ArmReply", "SetModeRequest", "SetModeReply",
    "LoadMissionRequest", "LoadMissionReply", "GetMissionReply", "EmergencyStopRequest", "EmergencyStopReply",
    "SelectPluginRequest", "SelectPluginReply", "VioResetRequest",
    # actions
    "TakeoffGoal", "TakeoffResult", "TakeoffFeedback", "LandGoal", "LandResult", "LandFeedback",
    "SetTrajectoryGoal", "SetTrajectoryResult", "SetTrajectoryFeedback", "GoToPositionGoal",
    "GoToPositionResult", "GoToPositionFeedback", "GoalStatus", "GoalReply", "CancelRequest",
    "CancelReply", "ResultRequest", "ActionFeedback", "ActionResult", "ActionSpec", "ACTIONS",
]

# stack infrastructure (sim clock, live parameters)
from .system import Clock, ParamDescriptor, ParamList, ParamSet, ParamSetReply  # noqa: E402

__all__ += ["Clock", "ParamDescriptor", "ParamList", "ParamSet", "ParamSetReply"]
