"""The one place a Trajectory message becomes a path, and the trajectory generators keyed by name
(the planner's `trajectory_generator` parameter; SetTrajectoryGenerator through
planner/srv/select_plugin; a mission may name its own in the message's `generator_name`).

`waypoint` is the planner's goal-by-goal P-controller (no path: it flies each goal as it comes);
`smooth` times the waypoints through blend.smooth. A typed or timed message is evaluated as given
and refused when it would exceed the limits by more than LIMIT_TOLERANCE.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from aeroperception.schemas import Trajectory
from aeroperception.schemas.mission import TRAJECTORY_GENERATORS

from .blend import CORNER_SHARE, smooth
from .core import KinematicLimits, Path, PlanningMargin, peaks
from .evaluate import TrajectoryRefused, evaluate

LIMIT_TOLERANCE = 0.10
FRAME = "map"             # the one frame trajectories are given in (ENU)


def _smooth(points_m: np.ndarray, yaws_rad: list[float | None], limits: KinematicLimits, acceptance_radius_m: float,
            start_velocity_mps: np.ndarray | None) -> Path:
    return smooth(points_m, limits, acceptance_radius_m, yaws_rad=yaws_rad, start_velocity_mps=start_velocity_mps)


@dataclass(frozen=True)
class Generator:
    description: str
    # (points from the vehicle on, yaws, limits, acceptance radius, the velocity to start at or None for
    # rest) -> path; None: flies goal by goal
    make: Callable[[np.ndarray, list, KinematicLimits, float, np.ndarray | None], Path] | None


GENERATORS: dict[str, Generator] = {
    "waypoint": Generator("goal by goal: the P-controller, stopping at each waypoint", None),
    "smooth": Generator("one jerk-limited trajectory through the waypoints (straight legs, blended corners)", _smooth),
}
if tuple(GENERATORS) != TRAJECTORY_GENERATORS:   # the names a mission file may give: one list
    raise ImportError(f"GENERATORS {tuple(GENERATORS)} differ from schemas.mission.TRAJECTORY_GENERATORS")


def generator_of(msg: Trajectory, active: str) -> str:
    """The generator an untimed WAYPOINT message is flown with: its own `generator_name`, else
    the planner's active one."""
    return msg.generator_name or active


def check_frames(msg: Trajectory) -> None:
    """Trajectories are flown in the map frame: any other frame is refused naming the field
    (never taken as map)."""
    if msg.header.frame_id not in ("", FRAME):
        raise TrajectoryRefused(f"`header.frame_id` {msg.header.frame_id!r}: trajectories are given in {FRAME!r}")
    for i, w in enumerate(msg.waypoints):
        if w.header.frame_id != FRAME:
            raise TrajectoryRefused(f"`waypoints[{i}].header.frame_id` {w.header.frame_id!r}: waypoints are "
                                    f"given in {FRAME!r}")


# a Trajectory's `limits` field -> (the KinematicLimits field it tightens, the planner parameter behind it)
OWN_LIMITS = {"max_velocity_mps": ("xy_vel_max_mps", "max_velocity_mps"), "acc_hor_mps2": ("acc_hor_mps2", "acc_hor_mps2"),
              "jerk_mps3": ("jerk_mps3", "jerk_mps3"), "z_vel_max_up_mps": ("z_vel_max_up_mps", "z_vel_max_up_mps"),
              "z_vel_max_dn_mps": ("z_vel_max_dn_mps", "z_vel_max_dn_mps")}


def limits_of(msg: Trajectory, limits: KinematicLimits) -> KinematicLimits:
    """The planner's `limits` tightened by the message's own; one above the planner's is refused
    naming the field (a mission asking for more than the vehicle is set up for is not clipped)."""
    if msg.limits is None:
        return limits
    tighter = {}
    for name, value in msg.limits.given().items():
        field, param = OWN_LIMITS[name]
        own = getattr(limits, field)
        if value > own * (1 + 1e-9):
            raise TrajectoryRefused(f"`limits.{name}` {value:g} is above the planner's {param} {own:g}")
        tighter[field] = value
    return dataclasses.replace(limits, **tighter)


def path_for(msg: Trajectory, position_m: np.ndarray, yaw_rad: float, limits: KinematicLimits,
             acceptance_radius_m: float, generator: str = "smooth", margin: PlanningMargin = PlanningMargin(),
             velocity_mps: np.ndarray | None = None) -> Path | None:
    """The path `msg` asks for, flown from `position_m` (an untimed WAYPOINT message starts there
    at `velocity_mps`, or at rest where a path cannot start so or none is given, and passes its
    waypoints in order), with `generator` unless the message names its
    own; None: that generator flies goal by goal. A generated path is planned inside the limits by
    the flight controller's `margin` (KinematicLimits.inside); a typed one is flown as given, checked
    against the limits themselves. Raises TrajectoryRefused naming the field."""
    check_frames(msg)
    limits = limits_of(msg, limits)
    if msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT and not msg.waypoint_times_s:
        name = generator_of(msg, generator)
        gen = GENERATORS.get(name)
        if gen is None:
            raise TrajectoryRefused(f"`generator_name` {name!r} is not a generator: {', '.join(GENERATORS)}")
        make_path = gen.make
        if make_path is None:
            return None
        for field in ("total_duration_s", "poly_order", "poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z",
                      "poly_coeffs_yaw"):
            if getattr(msg, field):
                raise TrajectoryRefused(f"`{field}` is not used by the {name} generator: leave it empty")
        if not msg.waypoints:
            raise TrajectoryRefused("`waypoints` is empty: nothing to fly")
        points = [np.asarray(position_m, float)] + [np.array([w.pose.position.x, w.pose.position.y, w.pose.position.z])
                                                    for w in msg.waypoints]
        yaws = [yaw_rad] + [w.pose.orientation.to_yaw() for w in msg.waypoints]
        planned = limits.inside(margin)

        def make(pts: list, yws: list) -> Path:
            """At the velocity given, else (the first leg cannot hold the blend from it) at rest."""
            if velocity_mps is not None and np.any(velocity_mps):
                try:
                    return make_path(np.array(pts), yws, planned, acceptance_radius_m, velocity_mps)
                except ValueError:
                    pass
            return make_path(np.array(pts), yws, planned, acceptance_radius_m, None)

        try:
            return make(points, yaws)
        except ValueError as e:
            error = e
        if np.linalg.norm(points[1] - points[0]) <= CORNER_SHARE * acceptance_radius_m:
            # Already at the first waypoint (hovering there, a mission resumed): a leg of centimetres
            # holds no blend; start at the waypoint, a step within the corner's own tolerance. The
            # vehicle's point keeps its place in waypoint_times_s (at 0 s, with waypoint 0).
            try:
                path = make(points[1:], [yaw_rad] + yaws[2:])
                path.waypoint_times_s = [0.0] + list(path.waypoint_times_s)
                return path
            except ValueError as e:
                error = e
        raise TrajectoryRefused(f"`waypoints`: {error}") from None
    path = evaluate(msg)
    gap = float(np.linalg.norm(path.sample(0.0).position_m - np.asarray(position_m, float)))
    if gap > max(1.0, acceptance_radius_m):
        raise TrajectoryRefused(f"the trajectory starts {gap:.1f} m from the vehicle: it must start where the "
                                f"vehicle is (within {max(1.0, acceptance_radius_m):.1f} m)")
    over = peaks(path, step_s=min(0.02, max(path.duration_s / 20000, 1e-3))).excess(limits, LIMIT_TOLERANCE)
    if over:
        raise TrajectoryRefused(f"the trajectory exceeds the planner's limits by more than "
                                f"{LIMIT_TOLERANCE:.0%}: {'; '.join(over)}")
    return path

