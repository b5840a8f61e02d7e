"""The trajectory the mission hands the planner (mission/active_trajectory).

While the mission flies its waypoints, the planner gets the whole way at once — the waypoints
from where this stretch of flying began — so its trajectory generator can fly through them instead
of stopping at each (the planner's `waypoint` generator still flies them goal by goal); the
mission still hands it one goal at a time (mission/active_goal) and counts each waypoint by the
vehicle's distance, exactly as before. Which generator: the mission file's `trajectory.generator`
in `generator_name`, else "" = the planner's active one (the planner owns that choice: one
value, switched by SetTrajectoryGenerator); the file's limits travel in `limits`.
The message stays the same for the whole stretch (the planner makes its path once); a hold, a
goto, a landing or a new start ends the stretch, and the next one starts from the waypoint then
current. A trajectory given through the SetTrajectory action is handed over as given while the
mission flies to its end (a goto there); anything else hands over an empty message: none.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.schemas import (
    Header, Pose, PoseStamped, Quaternion, SetTrajectoryGoal, Trajectory, TrajectoryLimits, TrajectoryStatus, Vector3,
)
from aeroperception.services.lib.trajectory import KinematicLimits, TrajectoryRefused
from aeroperception.services.lib.trajectory.generators import path_for

NONE = Trajectory()
TRAJECTORY_END_RADIUS_M = 0.3    # a given trajectory is done within this of its end (it ends at rest there)


def waypoint_pose(wp) -> PoseStamped:
    return PoseStamped(header=Header(frame_id="map"),
                       pose=Pose(position=Vector3(x=wp.x, y=wp.y, z=wp.z),
                                 orientation=Quaternion.from_yaw(math.radians(wp.yaw_deg))))


class TrajectoryHandover:
    """What mission/active_trajectory says now, from the manager's state (see the module doc)."""

    def __init__(self) -> None:
        self.start_index: int | None = None
        self._key: tuple | None = None
        self._msg: Trajectory = NONE
        self.given: tuple[Trajectory, np.ndarray] | None = None
        self.current: Trajectory = NONE         # what message() said last

    def give(self, msg: Trajectory, end_m: np.ndarray) -> None:
        """The SetTrajectory action's trajectory, flown while the mission's goto goes to `end_m`."""
        self.given = (msg, np.asarray(end_m, float).copy())

    def refused(self, status) -> bool:
        """Whether the planner's TrajectoryStatus says it refused (ABORTED) the trajectory handed over now."""
        return (status.status == TrajectoryStatus.STATUS_ABORTED and self.current is not NONE
                and status.trajectory_id == self.current.trajectory_id)

    def message(self, flying_waypoints: bool, mission, wp_index: int, goto_m: np.ndarray | None = None) -> Trajectory:
        """`flying_waypoints`: EXECUTING the mission's waypoints (not a goto, not holding);
        `goto_m`: EXECUTING a goto to there (None otherwise)."""
        self.current = self._message(flying_waypoints, mission, wp_index, goto_m)
        return self.current

    def _message(self, flying_waypoints: bool, mission, wp_index: int, goto_m: np.ndarray | None) -> Trajectory:
        if self.given is not None:
            if goto_m is not None and np.linalg.norm(np.asarray(goto_m) - self.given[1]) < 1e-6:
                return self.given[0]
            self.given = None                  # the goto ended or another took its place
        if not flying_waypoints or mission is None or wp_index >= len(mission.waypoints):
            self.start_index, self._key, self._msg = None, None, NONE
            return NONE
        if self.start_index is None:
            self.start_index = wp_index
        spec = mission.trajectory
        key = (mission.mission_id, self.start_index, spec)
        if key != self._key:
            self._key = key
            self._msg = Trajectory(
                header=Header(frame_id="map"), trajectory_id=f"{mission.mission_id}@{self.start_index}",
                generator_name=spec.generator if spec is not None else "",
                limits=TrajectoryLimits(**spec.given()) if spec is not None and spec.given() else None,
                trajectory_type=Trajectory.TRAJECTORY_WAYPOINT, setpoint_type=Trajectory.SETPOINT_FULL_STATE,
                waypoints=[waypoint_pose(w) for w in mission.waypoints[self.start_index:]])
        return self._msg


def check_given(goal: SetTrajectoryGoal, position_m: np.ndarray, yaw_rad: float,
                acceptance_radius_m: float) -> tuple[str, np.ndarray | None]:
    """("", the trajectory's end) when the SetTrajectory goal can be flown from here as given, else
    (why, None) naming the field. The planner checks it again against its own limits."""
    msg = goal.trajectory
    if not goal.replace_current:
        return "`replace_current` false (append to the current trajectory) is not supported: send it whole", None
    if msg.start_time_ns:
        return "`trajectory.start_time_ns`: a delayed start is not supported (0 = on receipt)", None
    if msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT and not msg.waypoint_times_s \
            and msg.generator_name != "smooth":
        # flown as a goto to its end: the goal-by-goal generator would skip the waypoints between
        return (f"`trajectory.generator_name` {msg.generator_name!r}: untimed waypoints are flown with 'smooth' "
                "(give it, or times, or fly them as a mission)"), None
    try:
        path = path_for(msg, position_m, yaw_rad, KinematicLimits(), acceptance_radius_m)
    except TrajectoryRefused as e:
        return f"trajectory refused: {e}", None
    end = path.sample(path.duration_s).position_m
    if np.linalg.norm(end - np.asarray(position_m, float)) < acceptance_radius_m:
        return ("the trajectory ends within the acceptance radius of where it starts: a loop cannot be "
                "told done by position (not supported)"), None
    return "", end
