"""On the ground or hovering: the one rule the planner (when a swappable part may be switched) and
the mission (the UAVMode a dashboard shows) judge a VehicleState by, and the hover speed parameter
behind it, declared once here: the planner's contract lists HOVER_SPEED_PARAM and the mission
starts from its default until the planner says its live value.
"""
from __future__ import annotations

import numpy as np

from aeroperception.schemas import VehicleState
from aeroperception.services.runtime import Param

HOVER_SPEED_PARAM = Param("hover_speed_mps", 0.3, "m/s", 0.05, 2.0,
                          description="in the air below this speed = hovering (a part may be switched)")


def speed_mps(state: VehicleState) -> float:
    return float(np.linalg.norm(state.velocity_mps.to_array()))


def on_ground(state: VehicleState) -> bool:
    return state.landed or not state.armed


def is_hovering(state: VehicleState, hover_speed_mps: float) -> bool:
    """In the air and (nearly) still: speed below `hover_speed_mps`."""
    return not on_ground(state) and speed_mps(state) < hover_speed_mps
