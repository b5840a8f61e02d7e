"""Mission manager messages: the mission file format (Mission, Waypoint), its status, the
operator's commands, the goal it hands the planner and the waypoint-reached event.

Mission/Waypoint are exactly requirement MIS-3's JSON (x/y/z in metres ENU, yaw_deg in degrees — the
only non-SI field names in the project, kept so existing mission files load unchanged).
`parse_mission` is the one place mission text (JSON or YAML) is validated; it never returns a
mission the vehicle cannot fly (no waypoints, non-finite numbers, non-positive radius or altitude).

State and command names are MIS-1's and MIS-5's strings (readable in logs and any language); the set of
commands is closed, so a typo is rejected at decode instead of being silently ignored by the FSM.
"""
from __future__ import annotations

from pathlib import Path

import msgspec

from ._base import Header, Message, SchemaError, check_known_fields, from_builtins, schema
from ._checks import check_choice, check_finite, check_positive
from .geometry import Pose, Vector3
from .planning import TrajectoryLimits

__all__ = [
    "Waypoint", "Mission", "parse_mission", "load_mission_file", "MissionStatus", "MissionCommand", "MissionGoal",
    "WaypointReached",
]


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
    `pose` (ENU, `header.frame_id` "map"); frame_id HOLD_FRAME ("hold") = stop and hold where you are.
    `max_speed_mps` caps the commanded speed for this goal (a goto's velocity_mps) and
    `max_vertical_speed_mps` its vertical part (a takeoff's climb or a landing's descent rate);
    0 = the planner's own limit."""

    header: Header = msgspec.field(default_factory=Header)
    pose: Pose = msgspec.field(default_factory=Pose)
    max_speed_mps: float = 0.0
    max_vertical_speed_mps: float = 0.0

    HOLD_FRAME = "hold"   # header.frame_id of a goal that means "stop and hold where you are"

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("max_speed_mps", "max_vertical_speed_mps"):
            value = getattr(self, name)
            check_finite(name, value)
            if value < 0:
                raise ValueError(f"field `{name}` must be >= 0 (0 = the planner's own limit), got {value!r}")


class Waypoint(msgspec.Struct, kw_only=True):
    """One mission waypoint: x/y/z metres ENU (z up, above the take-off point), yaw in degrees
    (ENU: 0 = East, counter-clockwise positive)."""

    x: float
    y: float
    z: float
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x", "y", "z", "yaw_deg"):
            check_finite(name, getattr(self, name))


TRAJECTORY_GENERATORS = ("waypoint", "smooth")


class MissionTrajectory(TrajectoryLimits, kw_only=True):
    """How the waypoints are flown: `generator` waypoint = goal by goal, stopping at each; smooth =
    one jerk-limited trajectory through them; "" (default) = the planner's active generator (its
    `trajectory_generator` parameter). The limits (TrajectoryLimits' fields) tighten the planner's
    own for this mission; above them the planner refuses the trajectory."""

    generator: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.generator and self.generator not in TRAJECTORY_GENERATORS:
            raise ValueError(f"field `generator` must be one of {', '.join(TRAJECTORY_GENERATORS)}, "
                             f"got {self.generator!r}")


@schema("Mission", 1)
class Mission(Message, kw_only=True):
    """A mission: take off, fly the waypoints in order. Requirement MIS-3's JSON, unchanged:

    {"mission_id": "survey_01", "takeoff_altitude_m": 5.0,
     "waypoints": [{"x": 0.0, "y": 0.0, "z": 5.0, "yaw_deg": 0.0}, ...],
     "waypoint_acceptance_radius_m": 0.5}

    `require_vio` overrides the mission service's default VIO gate for this mission when set;
    `trajectory` ({"generator": "smooth"}) how its waypoints are flown.
    """

    header: Header = msgspec.field(default_factory=Header)
    mission_id: str = ""
    takeoff_altitude_m: float = 3.0
    waypoints: list[Waypoint]
    waypoint_acceptance_radius_m: float = 0.5
    require_vio: bool | None = None
    trajectory: MissionTrajectory | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.waypoints:
            raise ValueError("field `waypoints` must contain at least one waypoint")
        check_positive("takeoff_altitude_m", self.takeoff_altitude_m)
        check_positive("waypoint_acceptance_radius_m", self.waypoint_acceptance_radius_m)

    def to_json(self) -> str:
        return msgspec.json.encode(self).decode()


_mission_json = msgspec.json.Decoder(Mission)


def parse_mission(text: str | bytes) -> Mission:
    """Parse and validate a mission, JSON or YAML (the same structure), strictly: a misspelt
    field such as `takeoff_altitude` is refused, not silently replaced by the default, and a
    missing one is named. The one place mission text is read (files, mission/srv/load, the
    mission service's start-up file, the persisted mission). JSON text (starting with `{`) goes
    through the JSON decoder, anything else through YAML (PyYAML reads `1e3` as a string, so
    JSON is never handed to it). SchemaError names the offending field (e.g. "Mission: Expected
    `float`, got `str` - at `$.waypoints[1].x`")."""
    if isinstance(text, (bytes, bytearray, memoryview)):
        text = bytes(text).decode("utf-8", errors="replace")
    if text.lstrip().startswith("{"):
        try:
            mission = _mission_json.decode(text)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise SchemaError(f"Mission: {e}") from None
        check_known_fields(msgspec.json.decode(text), Mission)
        return mission
    import yaml

    try:
        obj = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise SchemaError(f"Mission: neither JSON nor valid YAML: {' '.join(str(e).split())}") from None
    if not isinstance(obj, dict):
        raise SchemaError("Mission: expected a JSON object or a YAML mapping with `waypoints`, "
                          f"got {type(obj).__name__}")
    return from_builtins(obj, Mission, strict=True)


def load_mission_file(path: str | Path) -> Mission:
    """Load a mission from a .json, .yaml or .yml file (parse_mission reads either format)."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise SchemaError(f"Mission: cannot read {p}: {e.strerror or e}") from None
    return parse_mission(text)
