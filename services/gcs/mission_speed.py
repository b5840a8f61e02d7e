"""DO_CHANGE_SPEED in missions and as a command: the planner's live speed limit is the speed.

The stack's Mission has no speed, so DO_CHANGE_SPEED items do not go into it: the planner's live
speed limit (planner max_velocity_mps, PLN_MAX_VELOCITY) is the speed. `waypoint_speeds` gives,
per mission waypoint, the speed in force while flying to it (the last DO_CHANGE_SPEED item before
it; None = none yet, leave the planner's speed alone), and gcs applies it (SpeedSchedule) when the
mission starts or resumes at that waypoint and when the previous one is reached. Speed types 0
(air) and 1 (ground) both set it (a multicopter in still air); 2/3 (climb/descent) are accepted
and ignored (the planner has one 3-D limit). param2 -1 (or NaN) is "no change", -2 "back to the
planner's default".

Mission-scoped: a speed set for a mission (its DO_CHANGE_SPEED items, or a DO_CHANGE_SPEED
command while it flies) ends with the mission: the planner's speed from before is restored when
the mission completes (last waypoint reached), lands (LAND/RTL, aborted or not), is IDLE again,
or is replaced by another mission. A pause (HOLDING) keeps it. A DO_CHANGE_SPEED command outside
a mission stays in force (PLN_MAX_VELOCITY / MPC_XY_VEL_MAX show it).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as M

if TYPE_CHECKING:
    from .mission_items import Item

SPEED_TYPES_HORIZONTAL = (0, 1)     # DO_CHANGE_SPEED param1: airspeed, ground speed
SPEED_TYPES_VERTICAL = (2, 3)       # climb, descent speed: no separate limit here
SPEED_NO_CHANGE = -1.0
SPEED_DEFAULT = -2.0


def change_speed_value(speed_type: float, speed: float) -> float | None:
    """DO_CHANGE_SPEED (param1, param2) -> the planner speed it asks for: m/s > 0, SPEED_DEFAULT,
    or None (no change: -1, NaN, or a vertical speed type). ValueError(param index, reason) if
    invalid."""
    if not math.isfinite(speed_type) or int(speed_type) != speed_type or \
            int(speed_type) not in SPEED_TYPES_HORIZONTAL + SPEED_TYPES_VERTICAL:
        raise ValueError(1, f"speed type {speed_type} not supported")
    if int(speed_type) in SPEED_TYPES_VERTICAL:
        return None
    if not math.isfinite(speed) or speed == SPEED_NO_CHANGE:
        return None
    if speed == SPEED_DEFAULT:
        return SPEED_DEFAULT
    if speed <= 0:
        raise ValueError(2, f"speed {speed} m/s must be > 0 (or -1 no change, -2 default)")
    return float(speed)


def waypoint_speeds(items: list[Item], seqs: list[int]) -> list[float | None]:
    """Per mission waypoint (seqs: the item each came from, as convert_items returns them), the
    speed asked for by the last DO_CHANGE_SPEED item before it: m/s, SPEED_DEFAULT, or None."""
    out: list[float | None] = []
    speed: float | None = None
    i = 0
    for seq in seqs:
        while i < len(items) and items[i].seq < seq:
            it = items[i]
            if it.command == M.MAV_CMD_DO_CHANGE_SPEED:
                try:
                    v = change_speed_value(it.param1, it.param2)
                except ValueError:
                    v = None
                if v is not None:
                    speed = v
            i += 1
        out.append(speed)
    return out


class SpeedSchedule:
    """When to change the planner's speed for the loaded mission's DO_CHANGE_SPEED items:
    due(k) is the speed to apply now that the vehicle flies to waypoint k, None if nothing to do
    (no item before k, or already applied). reset() forgets what was applied (a new start).

    Scope: begin(current) remembers the planner's speed before the mission first changed it;
    observe(mission/status fields) returns, once the run is over, the speed to restore (and
    forgets it), else None. A run is over when another mission replaces it, or, after it was seen
    running (TAKEOFF / EXECUTING / HOLDING), when its last waypoint is reached or it lands or is
    IDLE; a start that fails ends it too (the caller restores)."""

    RUNNING = ("TAKEOFF", "EXECUTING", "HOLDING")

    def __init__(self, speeds: list[float | None] | None = None, mission_id: str = "",
                 restore: float | None = None):
        self.speeds = list(speeds or [])
        self.mission_id = mission_id
        self.applied: float | None = None
        self.restore = restore          # the planner's speed before this mission changed it
        self.running = False            # the run was seen under way since begin()

    def begin(self, current: float | None) -> None:
        if self.restore is None and current is not None:
            self.restore = float(current)
            self.running = False

    def end(self) -> float | None:
        """Forget the scope; the speed to restore (None if nothing was changed)."""
        speed, self.restore, self.running, self.applied = self.restore, None, False, None
        return speed

    def observe(self, mission_id: str, state: str, active_waypoint: int, total_waypoints: int) -> float | None:
        if self.restore is None:
            return None
        done = total_waypoints > 0 and active_waypoint >= total_waypoints
        if mission_id == self.mission_id and state in self.RUNNING and not done:
            self.running = True
            return None
        if mission_id != self.mission_id or (self.running and (done or state in ("IDLE", "LAND"))):
            return self.end()
        return None

    def reset(self) -> None:
        self.applied = None

    def due(self, k: int) -> float | None:
        if not 0 <= k < len(self.speeds):
            return None
        s = self.speeds[k]
        if s is None or s == self.applied:
            return None
        self.applied = s
        return s
