"""The one place a Trajectory message becomes a path.

Of the generators (schemas.mission.TRAJECTORY_GENERATORS), `waypoint` is the planner's goal-by-goal
P-controller (no path: it flies each goal as it comes) and `smooth` times the waypoints through
blend.smooth. A typed or timed message is evaluated as given
and refused when it would exceed the limits by more than LIMIT_TOLERANCE.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.schemas import Trajectory

from .blend import smooth
from .core import Limits, Path, peaks
from .evaluate import TrajectoryRefused, evaluate

LIMIT_TOLERANCE = 0.10


def path_for(msg: Trajectory, position_m: np.ndarray, yaw_rad: float, limits: Limits,
             acceptance_radius_m: float) -> Path:
    """The path `msg` asks for, flown from `position_m` (an untimed WAYPOINT message starts at
    rest there and passes its waypoints in order). Raises TrajectoryRefused naming the field."""
    if msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT and not msg.waypoint_times_s:
        if msg.generator_name != "smooth":
            raise TrajectoryRefused(f"`generator_name` {msg.generator_name!r} cannot time waypoints: generators: smooth "
                                    "(waypoint flies goal by goal and takes no trajectory)")
        for name in ("total_duration_s", "poly_order", "poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z",
                     "poly_coeffs_yaw"):
            if getattr(msg, name):
                raise TrajectoryRefused(f"`{name}` is not used by the smooth generator: leave it empty")
        if not msg.waypoints:
            raise TrajectoryRefused("`waypoints` is empty: nothing to fly")
        points = [np.asarray(position_m, float)] + [np.array([w.pose.position.x, w.pose.position.y, w.pose.position.z])
                                                    for w in msg.waypoints]
        yaws = [yaw_rad] + [w.pose.orientation.to_yaw() for w in msg.waypoints]
        try:
            return smooth(np.array(points), limits, acceptance_radius_m, yaws_rad=yaws)
        except ValueError as e:
            raise TrajectoryRefused(f"`waypoints`: {e}") from None
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


def limits_from(params) -> Limits:
    """The planner parameters that bound every trajectory (contract: PX4's MPC_* defaults)."""
    return Limits(xy_vel_max_mps=params["max_velocity_mps"], z_vel_max_up_mps=params["z_vel_max_up_mps"],
                  z_vel_max_dn_mps=params["z_vel_max_dn_mps"], acc_hor_mps2=params["acc_hor_mps2"],
                  acc_up_mps2=params["acc_up_mps2"], acc_down_mps2=params["acc_down_mps2"],
                  jerk_mps3=params["jerk_mps3"], yaw_rate_max_radps=math.radians(params["yaw_rate_max_dps"]))
