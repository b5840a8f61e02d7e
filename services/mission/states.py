"""The mission FSM's vocabulary: its 5 states (requirement MIS-1), the events that move it, and
the sub-state a HOLDING carries (why it holds). Names only: which event moves which state is
fsm.py's TRANSITIONS, the one place behaviour is declared."""
from __future__ import annotations

from enum import Enum


class State(str, Enum):
    IDLE = "IDLE"
    TAKEOFF = "TAKEOFF"
    EXECUTING = "EXECUTING"
    HOLDING = "HOLDING"
    LAND = "LAND"


class Event(str, Enum):
    TAKEOFF_CMD = "TAKEOFF_CMD"            # armed, takeoff requested
    ALTITUDE_REACHED = "ALTITUDE_REACHED"
    START_CMD = "START_CMD"
    HOLD_CMD = "HOLD_CMD"
    LAND_CMD = "LAND_CMD"
    RTL_CMD = "RTL_CMD"
    WAYPOINTS_DONE = "WAYPOINTS_DONE"
    GOTO_DONE = "GOTO_DONE"
    PERCEPTION_LOST = "PERCEPTION_LOST"
    PERCEPTION_RECOVERED = "PERCEPTION_RECOVERED"
    PERCEPTION_TIMEOUT = "PERCEPTION_TIMEOUT"
    LINK_LOST = "LINK_LOST"
    LANDED = "LANDED"
    BRIDGE_FAILED_AIR = "BRIDGE_FAILED_AIR"
    BRIDGE_FAILED_GROUND = "BRIDGE_FAILED_GROUND"
    FC_MODE_CHANGED = "FC_MODE_CHANGED"    # the FC left the mode we asked for, on its own
    FC_LANDED = "FC_LANDED"                # the FC landed and disarmed without our LAND
    FMU_OUTAGE = "FMU_OUTAGE"              # state/vehicle stale, fmu gone or FC link lost
    OUTAGE_RESUME = "OUTAGE_RESUME"        # fmu back and resume_after_outage set
    RESTARTED_IN_AIR = "RESTARTED_IN_AIR"  # this service (re)started over a flying vehicle
    SAFETY_HOLD = "SAFETY_HOLD"            # safety/status recommends HOLD
    SAFETY_RTH = "SAFETY_RTH"              # ... return home
    SAFETY_LAND = "SAFETY_LAND"            # ... land here
    GOAL_BLOCKED = "GOAL_BLOCKED"          # the planner cannot reach the goal: hold (blocked_action hold)
    GOAL_BLOCKED_RTL = "GOAL_BLOCKED_RTL"  # ... and blocked_action is rtl



class HoldReason(str, Enum):
    """Why the mission is HOLDING: what may end the hold by itself (PERCEPTION: perception back;
    OUTAGE: fmu back with resume_after_outage) and what only an operator ends (the others)."""

    NONE = ""
    PERCEPTION = "perception"
    LINK = "link"
    OUTAGE = "outage"
    FLIGHT_CONTROLLER = "flight controller"
    RESTART = "restart"
    SAFETY = "safety"
    BLOCKED = "blocked"


# The event that entered HOLDING -> why it holds (any other event: NONE, e.g. an operator HOLD).
HOLD_REASONS: dict[Event, HoldReason] = {
    Event.PERCEPTION_LOST: HoldReason.PERCEPTION,
    Event.LINK_LOST: HoldReason.LINK,
    Event.FMU_OUTAGE: HoldReason.OUTAGE,
    Event.FC_MODE_CHANGED: HoldReason.FLIGHT_CONTROLLER,
    Event.RESTARTED_IN_AIR: HoldReason.RESTART,
    Event.SAFETY_HOLD: HoldReason.SAFETY,
    Event.GOAL_BLOCKED: HoldReason.BLOCKED,
}
