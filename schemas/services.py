"""Request/reply pairs for Zenoh queryables (`<area>/srv/<name>`), the ROS services of requirements FC-3 and IF-3.

Every reply subclasses `Reply` (success + message), so a client can report any failure the same
way without knowing the service. Source types that meant the same thing are merged:
ArmVehicle + Arm -> ArmRequest/ArmReply; SetFlightMode -> SetModeRequest/SetModeReply;
SetController/SetEstimator/SetTrajectoryGenerator -> SelectPluginRequest/SelectPluginReply
(a `role` field says which plugin slot).
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema
from .geometry import Pose, Vector3
from ._checks import check_choice

__all__ = [
    "Empty", "Reply", "ArmRequest", "ArmReply", "SetModeRequest", "SetModeReply",
    "LoadMissionRequest", "LoadMissionReply", "GetMissionReply", "EmergencyStopRequest", "EmergencyStopReply",
    "SelectPluginRequest", "SelectPluginReply", "VioResetRequest",
]


@schema("Empty", 1)
class Empty(Message, kw_only=True):
    """Request of a parameterless queryable (only the header; `{}` decodes too)."""

    header: Header = msgspec.field(default_factory=Header)


@schema("Reply", 1)
class Reply(Message, kw_only=True):
    """Base of every reply: did it work, and a human-readable why (empty on plain success)."""

    header: Header = msgspec.field(default_factory=Header)
    success: bool = False
    message: str = ""


@schema("ArmRequest", 1)
class ArmRequest(Message, kw_only=True):
    """Arm (True) or disarm (False) the vehicle (fmu/srv/arm). `force` bypasses the
    autopilot's pre-arm checks / lets disarm happen in the air: for tests and emergencies only."""

    header: Header = msgspec.field(default_factory=Header)
    arm: bool  # required: an empty request must never arm the vehicle
    force: bool = False


@schema("ArmReply", 1)
class ArmReply(Reply, kw_only=True):
    """`armed` is the vehicle's arming state after the request (IF-3's Arm)."""

    armed: bool = False


@schema("SetModeRequest", 1)
class SetModeRequest(Message, kw_only=True):
    """Switch the autopilot's flight mode (fmu/srv/set_mode); `mode` is a nav_state name as in
    VehicleStatus ("OFFBOARD", "HOLD", "POSCTL", "LAND", "RTL", "TAKEOFF", "MISSION", ...)."""

    header: Header = msgspec.field(default_factory=Header)
    mode: str = ""


@schema("SetModeReply", 1)
class SetModeReply(Reply, kw_only=True):
    """`current_mode` is the mode after the request, whether or not it changed."""

    current_mode: str = ""


@schema("LoadMissionRequest", 1)
class LoadMissionRequest(Message, kw_only=True):
    """Load a mission (mission/srv/load); requirement MIS-3's JSON text, see planning.Mission."""

    header: Header = msgspec.field(default_factory=Header)
    mission_json: str = ""


@schema("LoadMissionReply", 1)
class LoadMissionReply(Reply, kw_only=True):
    """On failure `message` names the bad field (the source's error_message)."""

    num_waypoints: int = 0
    mission_id: str = ""


@schema("GetMissionReply", 1)
class GetMissionReply(Reply, kw_only=True):
    """The loaded mission (mission/srv/get, request Empty): MIS-3's JSON text, as loaded.
    success False (and empty fields) when no mission is loaded."""

    mission_id: str = ""
    num_waypoints: int = 0
    mission_json: str = ""


@schema("EmergencyStopRequest", 1)
class EmergencyStopRequest(Message, kw_only=True):
    """Stop the motors now (fmu/srv/emergency_stop): the vehicle falls. Ignored unless `confirm`."""

    header: Header = msgspec.field(default_factory=Header)
    confirm: bool = False
    reason: str = ""


@schema("EmergencyStopReply", 1)
class EmergencyStopReply(Reply, kw_only=True):
    """`success` is the source's `executed`."""


PLUGIN_ROLES = ("controller", "estimator", "trajectory_generator")


@schema("SelectPluginRequest", 1)
class SelectPluginRequest(Message, kw_only=True):
    """Activate plugin `name` in slot `role` (IF-3's SetController / SetEstimator /
    SetTrajectoryGenerator, which differ only in the slot)."""

    header: Header = msgspec.field(default_factory=Header)
    role: str = "controller"
    name: str = ""

    ROLE_CONTROLLER = "controller"
    ROLE_ESTIMATOR = "estimator"
    ROLE_TRAJECTORY_GENERATOR = "trajectory_generator"
    ROLES = PLUGIN_ROLES

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("role", self.role, PLUGIN_ROLES)


@schema("SelectPluginReply", 1)
class SelectPluginReply(Reply, kw_only=True):
    """`active` is the plugin active in the slot after the request (the source's active_controller /
    active_estimator / active_generator)."""

    active: str = ""


@schema("VioResetRequest", 1)
class VioResetRequest(Message, kw_only=True):
    """vio/srv/reset (reply: Reply): restart the visual odometry from a known pose (requirement
    VIO-6's warm start, e.g. a surveyed position after a companion reboot). `pose` is base_link
    in odom (ENU, FLU body), `velocity_mps` in odom; the default identity pose is a fresh start at
    the origin. VIO is INIT until its next good stereo frame, then TRACKING from that pose."""

    header: Header = msgspec.field(default_factory=Header)
    pose: Pose = msgspec.field(default_factory=Pose)
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
