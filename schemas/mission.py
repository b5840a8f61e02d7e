"""Mission manager messages: its status, the operator's commands, the perception gate it
listens to, and the waypoint-reached event.

State and command names are the seed 000 strings (readable in logs and any language); the set of
commands is closed, so a typo is rejected at decode instead of being silently ignored by the FSM.
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema
from ._checks import check_choice, check_finite, enum_names
from .geometry import Pose, Vector3

__all__ = ["MissionStatus", "MissionCommand", "MissionGoal", "PerceptionHealth", "WaypointReached"]


@schema("MissionStatus", 1)
class MissionStatus(Message, kw_only=True):
    """Where the mission FSM is (mission/status, 2 Hz). `active_waypoint` is 0-based, -1 when
    no mission runs; `distance_to_goal_m` is None without an active goal."""

    header: Header = msgspec.field(default_factory=Header)
    mission_id: str = ""
    state: str = "IDLE"
    active_waypoint: int = -1
    total_waypoints: int = 0
    elapsed_time_s: float = 0.0
    perception_healthy: bool = False
    distance_to_goal_m: float | None = None
    message: str = ""

    STATE_IDLE = "IDLE"
    STATE_TAKEOFF = "TAKEOFF"
    STATE_EXECUTING = "EXECUTING"
    STATE_HOLDING = "HOLDING"
    STATE_LAND = "LAND"
    STATES = ("IDLE", "TAKEOFF", "EXECUTING", "HOLDING", "LAND")


MISSION_COMMANDS = ("ARM", "DISARM", "TAKEOFF", "LOAD", "START", "HOLD", "LAND", "RTL", "SET_CURRENT")


@schema("MissionCommand", 1)
class MissionCommand(Message, kw_only=True):
    """An operator command to the mission manager (mission/command).

    `command` is one of MissionCommand.COMMANDS (case-insensitive on input, stored upper-case);
    `mission_json` carries the mission (JSON or YAML text) with LOAD and is empty otherwise.
    SET_CURRENT makes waypoint `waypoint_index` (0-based, required with it and only with it) the
    one flown to next, as a ground station's MISSION_SET_CURRENT does on PX4: at once when the
    mission is flying, else where START begins.
    """

    header: Header = msgspec.field(default_factory=Header)
    command: str
    mission_json: str = ""
    waypoint_index: int = -1

    ARM = "ARM"
    DISARM = "DISARM"
    TAKEOFF = "TAKEOFF"
    LOAD = "LOAD"
    START = "START"
    HOLD = "HOLD"
    LAND = "LAND"
    RTL = "RTL"
    SET_CURRENT = "SET_CURRENT"
    COMMANDS = MISSION_COMMANDS

    def __post_init__(self) -> None:
        super().__post_init__()
        self.command = self.command.strip().upper()
        check_choice("command", self.command, MISSION_COMMANDS)
        if self.command == "LOAD" and not self.mission_json.strip():
            raise ValueError("field `mission_json` is required with the LOAD command")
        if self.command == "SET_CURRENT" and self.waypoint_index < 0:
            raise ValueError("field `waypoint_index` (0-based, >= 0) is required with the SET_CURRENT command")
        if self.command != "SET_CURRENT" and self.waypoint_index != -1:
            raise ValueError(f"field `waypoint_index` is only for SET_CURRENT, not {self.command}")


@schema("PerceptionHealth", 1)
class PerceptionHealth(Message, kw_only=True):
    """The perception coordinator's verdict (perception/health, 1 Hz + on change): the single
    input the mission manager gates EXECUTING on. `overall_healthy` is vio_status == HEALTHY (true
    in a stack without VIO: nothing gates on it there).
    `lidar_status` (same enum; the LiDAR obstacle service's diagnostics) is reported, not gated on."""

    header: Header = msgspec.field(default_factory=Header)
    vio_status: int = 0
    detector_status: int = 0
    lidar_status: int = 0
    overall_healthy: bool = False
    message: str = ""

    UNKNOWN = 0
    INITIALIZING = 1
    HEALTHY = 2
    DEGRADED = 3
    FAILED = 4
    NOT_CONFIGURED = 5   # the stack runs no such source (e.g. `aero up --sensors camera`: no LiDAR)

    @classmethod
    def status_name(cls, value: int) -> str:
        return enum_names(cls).get(value, str(value))


@schema("WaypointReached", 1)
class WaypointReached(Message, kw_only=True):
    """Event: the vehicle came within the acceptance radius of waypoint `index` (0-based) of
    `mission_id`; `position_m` is where it was then (ENU)."""

    header: Header = msgspec.field(default_factory=Header)
    mission_id: str = ""
    index: int = 0
    position_m: Vector3 = msgspec.field(default_factory=Vector3)


@schema("MissionGoal", 1)
class MissionGoal(Message, kw_only=True):
    """The goal the mission hands the planner (mission/active_goal, on change + 2 Hz): fly to
    `pose` (ENU, `header.frame_id` "map"); frame_id "hold" = stop and hold where you are.
    `max_speed_mps` caps the commanded speed for this goal (a goto's velocity_mps) and
    `max_vertical_speed_mps` its vertical part (a takeoff's climb or a landing's descent rate);
    0 = the planner's own limit."""

    header: Header = msgspec.field(default_factory=Header)
    pose: Pose = msgspec.field(default_factory=Pose)
    max_speed_mps: float = 0.0
    max_vertical_speed_mps: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("max_speed_mps", "max_vertical_speed_mps"):
            value = getattr(self, name)
            check_finite(name, value)
            if value < 0:
                raise ValueError(f"field `{name}` must be >= 0 (0 = the planner's own limit), got {value!r}")
