"""What the mission asks the planner to fly: a goal (GoalOut), and a landing the planner flies
before the flight controller's LAND (LandPlan, in explicit phases). Plain data, ENU frame."""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np


@dataclass
class GoalOut:
    """What the planner should fly to: a position + yaw (ENU), or None = hold here."""

    position_m: np.ndarray | None
    yaw_rad: float | None = None
    acceptance_radius_m: float | None = None  # goto goals carry their own; None: the mission's
    max_speed_mps: float = 0.0                # the planner's caps for this goal (0: its own)
    max_vertical_speed_mps: float = 0.0


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
