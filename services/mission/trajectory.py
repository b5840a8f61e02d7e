"""The trajectory the mission hands the planner (mission/active_trajectory).

While the mission flies its waypoints with a trajectory generator other than `waypoint`, the
planner gets the whole way at once — the waypoints from where this stretch of flying began — so
it can fly through them instead of stopping at each; the mission still hands it one goal at a time
(mission/active_goal) and counts each waypoint by the vehicle's distance, exactly as before.
The message stays the same for the whole stretch (the planner makes its path once); a hold, a
goto, a landing or a new start ends the stretch, and the next one starts from the waypoint then
current. Anything else (or the `waypoint` generator) hands over an empty message: none.
"""
from __future__ import annotations

import math

from aeroperception.schemas import Header, Pose, PoseStamped, Quaternion, Trajectory, Vector3

NONE = Trajectory()


def waypoint_pose(wp) -> PoseStamped:
    return PoseStamped(header=Header(frame_id="map"),
                       pose=Pose(position=Vector3(x=wp.x, y=wp.y, z=wp.z),
                                 orientation=Quaternion.from_yaw(math.radians(wp.yaw_deg))))


class TrajectoryHandover:
    """What mission/active_trajectory says now, from the manager's state (see the module doc)."""

    def __init__(self, generator: str = "waypoint"):
        self.generator = generator
        self.start_index: int | None = None
        self._key: tuple | None = None
        self._msg: Trajectory = NONE

    def generator_for(self, mission) -> str:
        """The mission file's own choice, else the parameter's."""
        spec = getattr(mission, "trajectory", None)
        return spec.generator if spec is not None else self.generator

    def message(self, flying_waypoints: bool, mission, wp_index: int) -> Trajectory:
        """`flying_waypoints`: EXECUTING the mission's waypoints (not a goto, not holding)."""
        generator = self.generator_for(mission) if mission is not None else self.generator
        if not flying_waypoints or generator == "waypoint" or mission is None or wp_index >= len(mission.waypoints):
            self.start_index, self._key, self._msg = None, None, NONE
            return NONE
        if self.start_index is None:
            self.start_index = wp_index
        key = (mission.mission_id, self.start_index, generator)
        if key != self._key:
            self._key = key
            self._msg = Trajectory(
                header=Header(frame_id="map"), trajectory_id=f"{mission.mission_id}@{self.start_index}",
                generator_name=generator, trajectory_type=Trajectory.TRAJECTORY_WAYPOINT,
                setpoint_type=Trajectory.SETPOINT_FULL_STATE,
                waypoints=[waypoint_pose(w) for w in mission.waypoints[self.start_index:]])
        return self._msg
