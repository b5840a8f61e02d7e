"""Trajectories, planner status, collision constraints, and the mission file format.

Mission/Waypoint are exactly seed 000 §5.1's JSON (x/y/z in metres ENU, yaw_deg in degrees — the
only non-SI field names in the project, kept so existing mission files load unchanged).
`parse_mission` is the one place mission text (JSON or YAML) is validated; it never returns a
mission the vehicle cannot fly (no waypoints, non-finite numbers, non-positive radius or altitude).
"""
from __future__ import annotations

from pathlib import Path

import msgspec

from ._base import Header, Message, SchemaError, check_known_fields, from_builtins, schema
from ._checks import check_finite, check_positive
from .geometry import PoseStamped, Vector3
from .vehicle import TrajectorySetpoint

__all__ = [
    "Trajectory", "TrajectoryStatus", "CollisionConstraint", "Waypoint", "Mission",
    "parse_mission", "load_mission_file",
]


@schema("Trajectory", 1)
class Trajectory(Message, kw_only=True):
    """A complete trajectory for the planner to follow; `trajectory_type` says which part is used.

    Seed 002 Trajectory: its start_time/duration/total_duration_s become `start_time_ns`
    (same clock as header.stamp_ns, 0 = start on receipt) and `total_duration_s`.
    Waypoints are ENU poses; `waypoint_times_s`, when given, has one entry per waypoint
    (seconds from start). Polynomial coefficients are lowest order first.
    """

    header: Header = msgspec.field(default_factory=Header)
    trajectory_id: str = ""
    generator_name: str = ""

    trajectory_type: int = 0
    TRAJECTORY_WAYPOINT = 0
    TRAJECTORY_POLYNOMIAL = 1
    TRAJECTORY_BSPLINE = 2
    TRAJECTORY_BEZIER = 3

    start_time_ns: int = 0
    total_duration_s: float = 0.0

    waypoints: list[PoseStamped] = []
    waypoint_times_s: list[float] = []

    poly_coeffs_x: list[float] = []
    poly_coeffs_y: list[float] = []
    poly_coeffs_z: list[float] = []
    poly_coeffs_yaw: list[float] = []
    poly_order: int = 0

    setpoint_type: int = 0
    SETPOINT_POSITION_ONLY = 0
    SETPOINT_POSITION_YAW = 1
    SETPOINT_FULL_STATE = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.waypoint_times_s and len(self.waypoint_times_s) != len(self.waypoints):
            raise ValueError(
                f"field `waypoint_times_s` has {len(self.waypoint_times_s)} entries for {len(self.waypoints)} waypoints"
            )


@schema("TrajectoryStatus", 1)
class TrajectoryStatus(Message, kw_only=True):
    """Progress of the goal being flown (planner/status, 10 Hz).

    progress_percent: share of the leg flown, from where the vehicle was when the goal began to
    the goal's acceptance radius; elapsed_time_s: since the goal began (frozen on arrival);
    remaining_time_s: the distance left at the planner's commanded speed profile;
    current_setpoint: the setpoint last sent to fmu; position_error_m: distance from the vehicle
    to the goal (holding: to the hold point); velocity_error_mps: |current_setpoint velocity -
    vehicle velocity|. Without a goal the progress fields are 0."""

    header: Header = msgspec.field(default_factory=Header)
    trajectory_id: str = ""
    progress_percent: float = 0.0  # 0..100
    elapsed_time_s: float = 0.0
    remaining_time_s: float = 0.0
    current_setpoint: TrajectorySetpoint = msgspec.field(default_factory=TrajectorySetpoint)
    position_error_m: float = 0.0
    velocity_error_mps: float = 0.0
    # Obstacle handling: "off", "no_costmap", "stale_costmap", "clear", "avoiding", "planning", "blocked", "unreachable"; why.
    obstacle_state: str = ""
    message: str = ""

    status: int = 0
    STATUS_IDLE = 0
    STATUS_EXECUTING = 1
    STATUS_PAUSED = 2
    STATUS_COMPLETED = 3
    STATUS_ABORTED = 4
    STATUS_ERROR = 5


@schema("CollisionConstraint", 1)
class CollisionConstraint(Message, kw_only=True):
    """A region the vehicle must stay out of (multi-agent coordination), ENU.

    Half-plane: allowed where normal . p <= offset_m. Sphere: keep out of `center_m`/`radius_m`.
    Polygon: keep out of the prism over `polygon_m` (seed 002 names the type but gives no field).
    `expires_at_ns` is on the header's clock (0 = never).
    """

    header: Header = msgspec.field(default_factory=Header)
    constraint_type: int = 0
    CONSTRAINT_HALFPLANE = 0
    CONSTRAINT_SPHERE = 1
    CONSTRAINT_POLYGON = 2

    normal: Vector3 = msgspec.field(default_factory=Vector3)
    offset_m: float = 0.0
    center_m: Vector3 = msgspec.field(default_factory=Vector3)
    radius_m: float = 0.0
    polygon_m: list[Vector3] = []
    source_uav_id: str = ""
    confidence: float = 0.0  # 0..1
    expires_at_ns: int = 0


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


@schema("Mission", 1)
class Mission(Message, kw_only=True):
    """A mission: take off, fly the waypoints in order. Seed 000 §5.1's JSON, unchanged:

    {"mission_id": "survey_01", "takeoff_altitude_m": 5.0,
     "waypoints": [{"x": 0.0, "y": 0.0, "z": 5.0, "yaw_deg": 0.0}, ...],
     "waypoint_acceptance_radius_m": 0.5}

    `require_vio` overrides the mission service's default VIO gate for this mission when set.
    """

    header: Header = msgspec.field(default_factory=Header)
    mission_id: str = ""
    takeoff_altitude_m: float = 3.0
    waypoints: list[Waypoint]
    waypoint_acceptance_radius_m: float = 0.5
    require_vio: bool | None = None

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
