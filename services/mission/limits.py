"""What the mission service accepts to fly: every mission, goto goal and takeoff altitude is
checked here against the shared geofence (services/lib/geofence.py) and the mission's own
limits before it is accepted, so nothing unsafe ever reaches the planner.

Never a second geofence: the fence comes from the GEOFENCE_PARAMS the contract declares.
A waypoint inside an obstacle the costmap already shows is warned about at load (the costmap is
local and rolling: what it does not show yet is the planner's verdict in flight, blocked_action).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from aeroperception.schemas import Mission, OccupancyGrid
from aeroperception.services.lib.costmap import BLOCKED
from aeroperception.services.lib.geofence import Geofence
from aeroperception.services.runtime import Param
from aeroperception.services.runtime.config import build, param, section

from . import contract

@dataclass(frozen=True)
class Limits:
    """The mission parameters of the same names (defaults declared once, in contract.PARAMS;
    runtime/config.py builds it, the geofence a section of it)."""

    geofence: Geofence = section(Geofence)
    max_takeoff_altitude_m: float = param("max_takeoff_altitude_m")
    min_acceptance_radius_m: float = param("min_acceptance_radius_m")
    max_acceptance_radius_m: float = param("max_acceptance_radius_m")

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | Iterable[Param] = contract.PARAMS, **overrides: Any) -> "Limits":
        """From parameter values (default: the declared defaults); `overrides` by field name."""
        return build(cls, params, **overrides)

    def check_takeoff(self, altitude_m: float, x: float = 0.0, y: float = 0.0) -> str | None:
        """Why a takeoff to `altitude_m` (ENU z) from (x, y) is refused, or None."""
        if not math.isfinite(altitude_m):
            return "takeoff altitude is not finite"
        ceiling = min(self.max_takeoff_altitude_m, self.geofence.max_altitude_m)
        if altitude_m > ceiling:
            return (f"takeoff altitude {altitude_m:g} m is above the limit {ceiling:g} m "
                    f"(max_takeoff_altitude_m / geofence ceiling)")
        why = self.geofence.check_waypoint(x, y, altitude_m)
        return f"takeoff altitude: {why}" if why else None

    def check_acceptance_radius(self, radius_m: float) -> str | None:
        lo, hi = self.min_acceptance_radius_m, self.max_acceptance_radius_m
        if not math.isfinite(radius_m) or not lo <= radius_m <= hi:
            return f"acceptance radius {radius_m:g} m is outside {lo:g}..{hi:g} m"
        return None

    def check_goto(self, x: float, y: float, z: float, radius_m: float | None) -> str | None:
        why = self.geofence.check_waypoint(x, y, z)
        if why:
            return f"goto target: {why}"
        return self.check_acceptance_radius(radius_m) if radius_m is not None else None

    def check_mission(self, mission: Mission) -> str | None:
        """Why `mission` is refused (naming the waypoint index), or None if it may be flown."""
        why = self.check_takeoff(mission.takeoff_altitude_m)
        if why:
            return why
        why = self.check_acceptance_radius(mission.waypoint_acceptance_radius_m)
        if why:
            return f"waypoint_acceptance_radius_m: {why}"
        for i, wp in enumerate(mission.waypoints):
            why = self.geofence.check_waypoint(wp.x, wp.y, wp.z)
            if why:
                return f"waypoint {i} ({wp.x:g}, {wp.y:g}, {wp.z:g}): {why}"
        return None


def waypoints_in_obstacles(mission: Mission, costmap: OccupancyGrid | None) -> list[str]:
    """The waypoints the costmap already shows inside an obstacle (lethal or inscribed cell, as
    the planner judges them), each described for the operator; [] without a costmap or when
    every waypoint is outside it or free. The planner could never reach them."""
    if costmap is None or costmap.width == 0 or costmap.height == 0:
        return []
    cells = costmap.data.to_numpy()
    ox, oy, res = costmap.origin.position.x, costmap.origin.position.y, costmap.resolution_m
    out = []
    for i, wp in enumerate(mission.waypoints):
        col, row = math.floor((wp.x - ox) / res), math.floor((wp.y - oy) / res)
        if 0 <= row < costmap.height and 0 <= col < costmap.width and cells[row, col] >= BLOCKED:
            out.append(f"waypoint {i + 1} ({wp.x:g}, {wp.y:g}, {wp.z:g})")
    return out


def obstacle_warning(inside: list[str]) -> str:
    """What a load's reply adds for the waypoints_in_obstacles found ('' for none)."""
    return f"; warning: the costmap shows {', '.join(inside)} inside an obstacle: unreachable" if inside else ""
