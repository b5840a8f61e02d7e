"""What the mission asks the planner to fly: a goal (GoalOut, as a MissionGoal message), and a
landing the planner flies before the flight controller's LAND (LandPlan, in explicit phases).
Plain data, ENU frame."""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from aeroperception.schemas import Header, MissionGoal, Pose, Quaternion, Vector3


@dataclass
class GoalOut:
    """What the planner should fly to: a position + yaw (ENU), or None = hold here."""

    position_m: np.ndarray | None
    yaw_rad: float | None = None
    acceptance_radius_m: float | None = None  # goto goals carry their own; None: the mission's
    max_speed_mps: float = 0.0                # the planner's caps for this goal (0: its own)
    max_vertical_speed_mps: float = 0.0


def goal_message(goal: GoalOut, vehicle_yaw_rad: float | None, header: Header) -> MissionGoal:
    """mission/active_goal for `goal` (header's frame_id set here): hold, or the position with
    the goal's yaw (else the vehicle's, else 0)."""
    if goal.position_m is None:
        header.frame_id = MissionGoal.HOLD_FRAME
        return MissionGoal(header=header)
    header.frame_id = "map"
    yaw = goal.yaw_rad if goal.yaw_rad is not None else (vehicle_yaw_rad if vehicle_yaw_rad is not None else 0.0)
    return MissionGoal(header=header, pose=Pose(position=Vector3.from_array(goal.position_m),
                                                orientation=Quaternion.from_yaw(yaw)),
                       max_speed_mps=goal.max_speed_mps, max_vertical_speed_mps=goal.max_vertical_speed_mps)


class LandPhase(str, Enum):
    """The phases of a LandPlan, in order (APPROACH is skipped when landing here)."""

    APPROACH = "approach"   # to above the target at the altitude the landing started at
    DESCEND = "descend"     # down at the descent rate to land_handoff_altitude_m above the target
    FC = "fc"               # the flight controller's LAND (or RTL) from there


@dataclass
class LandPlan:
    """A landing flown by the planner first (LandGoal target / descent rate): to above the target
    (approach), down at the descent rate to land_handoff_altitude_m above it (descend), then the
    flight controller's LAND (fc)."""

    target_m: np.ndarray                      # the landing point: x, y and the ground's z there
    approach_z_m: float
    descent_rate_mps: float = 0.0
    phase: LandPhase = LandPhase.APPROACH
