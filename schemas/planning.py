"""Trajectories, planner status and collision constraints: what the planner flies and reports.

The mission file format (Mission, Waypoint) is the mission service's: schemas/mission.py.
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema
from ._checks import check_positive
from .geometry import PoseStamped, Vector3
from .vehicle import TrajectorySetpoint

__all__ = ["TrajectoryLimits", "Trajectory", "TrajectoryStatus", "CollisionConstraint"]


class TrajectoryLimits(msgspec.Struct, kw_only=True):
    """Tighter kinematic limits for one trajectory (a mission file's `trajectory` section, a
    Trajectory's `limits`), named after the planner's parameters (PX4's MPC_*); None = the
    planner's own. A value above the planner's own is refused naming the field, never clipped."""

    max_velocity_mps: float | None = None     # MPC_XY_VEL_MAX
    acc_hor_mps2: float | None = None         # MPC_ACC_HOR
    jerk_mps3: float | None = None            # MPC_JERK_AUTO
    z_vel_max_up_mps: float | None = None     # MPC_Z_VEL_MAX_UP
    z_vel_max_dn_mps: float | None = None     # MPC_Z_VEL_MAX_DN

    def __post_init__(self) -> None:
        for name in TrajectoryLimits.__struct_fields__:
            value = getattr(self, name)
            if value is not None:
                check_positive(name, value)

    def given(self) -> dict[str, float]:
        """{field: value} of the limits set."""
        return {n: getattr(self, n) for n in TrajectoryLimits.__struct_fields__ if getattr(self, n) is not None}


@schema("Trajectory", 1)
class Trajectory(Message, kw_only=True):
    """A complete trajectory for the planner to follow; `trajectory_type` says which part is used.

    IF-2's Trajectory: its start_time/duration/total_duration_s become `start_time_ns`
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

    # tighter limits for this trajectory (None: the planner's own)
    limits: TrajectoryLimits | None = None

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
    vehicle velocity|. Without a goal the progress fields are 0. `active_*`: the planner's parts
    running now (its trajectory_generator / controller / estimator, what UAVStatus reports);
    a refused SetTrajectory trajectory is STATUS_ABORTED under its own trajectory_id, `message` why."""

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
    active_trajectory_generator: str = ""
    active_controller: str = ""
    active_estimator: str = ""

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
    Polygon: keep out of the prism over `polygon_m` (IF-2 names the type but gives no field).
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
