"""The 5-state mission FSM of requirement MIS-1 as an explicit transition table, free of Zenoh.

States IDLE, TAKEOFF, EXECUTING, HOLDING, LAND (states.py). Everything that happens is an Event; the
only way the state changes is TRANSITIONS[(state, event)] below, the one place behaviour is declared.
Side effects (bridge calls, goal publication) go through the injected Bridge and `publish_goal`, so
tests drive the whole FSM with plain objects. A bridge call that fails is MIS-1's error path: in the
air the vehicle holds (planner keeps streaming), on the ground it goes back to IDLE, reason reported.

MissionManager is this table, each state's entry actions and the flight itself (takeoff, waypoint
progress, status); each other behaviour is its own module, a mixin of MissionManager named after it
and tested by its own file (tests/unit/test_mission_<behaviour>.py):
- operator.py: operator requests (LOAD, START, HOLD, LAND, RTL, ARM/DISARM, goto, SET_CURRENT);
- fc_authority.py: the flight controller has the last word (it leaves our mode: hold, never fight);
- outage.py: fmu or planner outage (hold; resume only when told, or by resume_after_outage);
- restart.py: persistence, restore() and the rebuild on the first vehicle state;
- perception_gate.py: hold / resume / RTL on perception (VIO) health;
- blocked_goal.py: a goal the planner reports blocked or unreachable;
- landing.py: LAND, the FC's or a LandPlan flown by the planner first.
safety/status (here, on_safety): a rising recommended_action HOLD / RTH / LAND acts once
(SAFETY_REACTIONS); the operator may command afterwards. EMERGENCY_STOP is the safety service's
own job. Every automatic transition is reported in `message`; parameters, units and defaults:
contract.py.

Operator requests answer through an Outcome (settled at once, or when the flight controller
has answered); what a running takeoff/land/goto action reports is actions.py's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from aeroperception.schemas import LandedState, Mission, MissionStatus, SafetyStatus, VehicleState

from aeroperception.services.lib.safety_names import ACTION_NAMES
from aeroperception.services.runtime import Param
from aeroperception.services.runtime.config import build, param

from . import contract
from .blocked_goal import BLOCKED_ACTIONS, BLOCKED_STATES, BlockedGoal  # noqa: F401 - re-exported
from .fc_authority import FcAuthority
from .goals import GoalOut, LandPhase, LandPlan  # noqa: F401 - re-exported
from .landing import RTL_EVENTS, Landing  # noqa: F401 - re-exported
from .limits import Limits
from .operator import OperatorCommands
from .outage import Outage, OutageWatch
from .perception_gate import PerceptionGate
from .requests import Bridge, Outcome
from .restart import PendingRestore, Restart
from .states import HOLD_REASONS, Event, HoldReason, State

S, E = State, Event
TRANSITIONS: dict[tuple[State, Event], State] = {
    (S.IDLE, E.TAKEOFF_CMD): S.TAKEOFF,
    (S.TAKEOFF, E.ALTITUDE_REACHED): S.HOLDING,     # then START (already requested or later)
    (S.TAKEOFF, E.HOLD_CMD): S.HOLDING,
    (S.TAKEOFF, E.LAND_CMD): S.LAND,
    (S.TAKEOFF, E.RTL_CMD): S.LAND,
    (S.TAKEOFF, E.LINK_LOST): S.HOLDING,
    (S.TAKEOFF, E.BRIDGE_FAILED_AIR): S.HOLDING,
    (S.TAKEOFF, E.BRIDGE_FAILED_GROUND): S.IDLE,
    (S.HOLDING, E.START_CMD): S.EXECUTING,
    (S.HOLDING, E.PERCEPTION_RECOVERED): S.EXECUTING,
    (S.HOLDING, E.LAND_CMD): S.LAND,
    (S.HOLDING, E.RTL_CMD): S.LAND,
    (S.HOLDING, E.PERCEPTION_TIMEOUT): S.LAND,
    (S.HOLDING, E.BRIDGE_FAILED_GROUND): S.IDLE,
    (S.EXECUTING, E.HOLD_CMD): S.HOLDING,
    (S.EXECUTING, E.PERCEPTION_LOST): S.HOLDING,
    (S.EXECUTING, E.LINK_LOST): S.HOLDING,
    (S.EXECUTING, E.GOTO_DONE): S.HOLDING,
    (S.EXECUTING, E.WAYPOINTS_DONE): S.LAND,
    (S.EXECUTING, E.LAND_CMD): S.LAND,
    (S.EXECUTING, E.RTL_CMD): S.LAND,
    (S.EXECUTING, E.BRIDGE_FAILED_AIR): S.HOLDING,
    (S.LAND, E.LANDED): S.IDLE,
    (S.LAND, E.HOLD_CMD): S.HOLDING,
    (S.LAND, E.BRIDGE_FAILED_AIR): S.HOLDING,
    (S.LAND, E.BRIDGE_FAILED_GROUND): S.IDLE,
    # the flight controller has the last word
    (S.TAKEOFF, E.FC_MODE_CHANGED): S.HOLDING,
    (S.EXECUTING, E.FC_MODE_CHANGED): S.HOLDING,
    (S.LAND, E.FC_MODE_CHANGED): S.HOLDING,         # a pilot took over the landing
    (S.TAKEOFF, E.FC_LANDED): S.IDLE,
    (S.EXECUTING, E.FC_LANDED): S.IDLE,
    (S.HOLDING, E.FC_LANDED): S.IDLE,
    # fmu outage and restart
    (S.TAKEOFF, E.FMU_OUTAGE): S.HOLDING,         # fmu or planner outage
    (S.EXECUTING, E.FMU_OUTAGE): S.HOLDING,
    (S.HOLDING, E.OUTAGE_RESUME): S.EXECUTING,
    (S.IDLE, E.RESTARTED_IN_AIR): S.HOLDING,
    # safety/status recommendations (airborne states only; a landing is never turned into a hold)
    (S.TAKEOFF, E.SAFETY_HOLD): S.HOLDING,
    (S.EXECUTING, E.SAFETY_HOLD): S.HOLDING,
    (S.TAKEOFF, E.SAFETY_RTH): S.LAND,
    (S.EXECUTING, E.SAFETY_RTH): S.LAND,
    (S.HOLDING, E.SAFETY_RTH): S.LAND,
    (S.TAKEOFF, E.SAFETY_LAND): S.LAND,
    (S.EXECUTING, E.SAFETY_LAND): S.LAND,
    (S.HOLDING, E.SAFETY_LAND): S.LAND,
    # the planner cannot reach the goal (planner/status blocked or unreachable for blocked_timeout_s)
    (S.EXECUTING, E.GOAL_BLOCKED): S.HOLDING,
    (S.EXECUTING, E.GOAL_BLOCKED_RTL): S.LAND,
}

# safety/status recommended_action -> the event it fires (on a rising recommendation only).
SAFETY_REACTIONS: dict[int, Event] = {
    SafetyStatus.ACTION_HOLD: E.SAFETY_HOLD,
    SafetyStatus.ACTION_RTH: E.SAFETY_RTH,
    SafetyStatus.ACTION_LAND: E.SAFETY_LAND,
}


@dataclass(frozen=True)
class Config:
    """The FSM's settings: each is the mission parameter of the same name (its default, unit and
    range are declared once, in contract.PARAMS; runtime/config.py builds it)."""

    takeoff_altitude_m: float = param("takeoff_altitude_m")
    altitude_tolerance_m: float = param("altitude_tolerance_m")
    require_perception: bool = param("require_perception")
    perception_timeout_s: float = param("perception_timeout_s")     # no perception/health this long = unhealthy
    perception_recovery_s: float = param("perception_recovery_s")   # recover within this or RTL
    land_on_complete: bool = param("land_on_complete")
    disarm_after_landing_s: float = param("disarm_after_landing_s")
    vehicle_timeout_s: float = param("vehicle_timeout_s")           # state/vehicle older than this = fmu outage
    resume_after_outage: bool = param("resume_after_outage")
    restore_timeout_s: float = param("restore_timeout_s")
    blocked_timeout_s: float = param("blocked_timeout_s")
    blocked_action: str = param("blocked_action")                   # hold | skip | rtl
    land_handoff_altitude_m: float = param("land_handoff_altitude_m")

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | Iterable[Param] = contract.PARAMS, **overrides: Any) -> "Config":
        """From parameter values (default: the declared defaults); `overrides` by field name."""
        return build(cls, params, **overrides)


class MissionManager(OperatorCommands, FcAuthority, OutageWatch, Restart, PerceptionGate, BlockedGoal, Landing):
    """The mission FSM: inputs (on_*, tick, operator requests) fire Events; TRANSITIONS moves the
    state; each state's _enter_<state> does its side effects."""

    def __init__(self, bridge: Bridge, publish_goal: Callable[[GoalOut], None],
                 config: Config | None = None, log: Callable[..., None] | None = None,
                 limits: Limits | None = None):
        self.bridge = bridge
        self.publish_goal = publish_goal
        self.cfg = config or Config.from_params()
        self.limits = limits or Limits.from_params()
        self.log = log or (lambda *a, **k: None)
        self.state = State.IDLE
        self.mission: Mission | None = None
        self.wp_index = -1
        self.start_requested = False
        self.takeoff_pending = False            # arming for a takeoff is in flight
        self.goto_target: GoalOut | None = None
        self.takeoff_altitude_m: float | None = None
        self.takeoff_goal: GoalOut | None = None  # where the takeoff ends: held after ALTITUDE_REACHED
        self.climb_rate_mps = 0.0               # the takeoff's climb rate cap (0: the planner's)
        self.land_plan: LandPlan | None = None  # a landing the planner flies before the FC's LAND
        self.vehicle: VehicleState | None = None
        self.vehicle_rx_s: float | None = None
        self.last_tick_s: float | None = None
        self.awake_since_s: float | None = None
        self.armed_seen = False                 # armed since entering TAKEOFF (FC_LANDED guard)
        self.perception_healthy = False
        self.perception_rx_s: float | None = None
        self.hold_reason = HoldReason.NONE         # why HOLDING (sub-state)
        self.hold_since_s = 0.0
        self.land_mode = "LAND"
        self.on_ground_since_s: float | None = None
        self.disarm_sent = False
        self.expected_mode: str | None = None   # the FC mode we asked for last
        self.mode_confirmed = False             # ... and the FC has been seen in it
        self.fmu_alive = True
        self.planner_alive = True               # unknown until its token is seen: assume up
        self.fmu_outage: Outage | None = None   # an fmu/planner outage in progress (`outage`: why)
        self.safety_action = SafetyStatus.ACTION_NONE
        self.pending_restore: PendingRestore | None = None  # restored: the first vehicle state rebuilds us
        self.resume_outcome: Outcome | None = None  # START's, settled by the OFFBOARD answer
        self.blocked_since_s: float | None = None   # planner/status blocked/unreachable since (this goal)
        self.message = "ready"
        self.started_s: float | None = None
        self.now_s = 0.0
        self.transitions: list[tuple[State, Event, State]] = []
        self.reached_events: list[int] = []
        self.on_waypoint_reached: Callable[[int, np.ndarray], None] = lambda i, p: None
        self.on_persist: Callable[[dict], None] = lambda snapshot: None

    # ------------------------------------------------------------ FSM core: the table, entry actions

    def fire(self, event: Event, reason: str = "") -> bool:
        nxt = TRANSITIONS.get((self.state, event))
        if nxt is None:
            return False
        prev, self.state = self.state, nxt
        self.transitions.append((prev, event, nxt))
        self.message = reason or f"{event.value.lower()}"
        self.log("transition", frm=prev.value, trigger=event.value, to=nxt.value, reason=reason)
        getattr(self, f"_enter_{nxt.value.lower()}")(prev, event)
        self._persist()
        return True

    def _enter_idle(self, prev: State, event: Event) -> None:
        self.start_requested = False
        self.goto_target = None
        self.takeoff_altitude_m = None
        self.takeoff_goal = None
        self.climb_rate_mps = 0.0
        self.land_plan = None
        self.expected_mode = None
        self.publish_goal(GoalOut(None))

    def _enter_takeoff(self, prev: State, event: Event) -> None:
        pos = self._position()
        alt = self.takeoff_altitude_m or (self.mission.takeoff_altitude_m if self.mission else self.cfg.takeoff_altitude_m)
        self.takeoff_altitude_m = alt
        self.started_s = self.now_s
        self.armed_seen = bool(self.vehicle and self.vehicle.armed)
        self.takeoff_goal = GoalOut(np.array([pos[0], pos[1], alt]), self.vehicle.yaw_rad if self.vehicle else None,
                                    max_vertical_speed_mps=self.climb_rate_mps)
        self.publish_goal(self.takeoff_goal)
        self._request_mode("OFFBOARD")

    def _enter_holding(self, prev: State, event: Event) -> None:
        self.hold_since_s = self.now_s
        self.land_plan = None
        self.hold_reason = HOLD_REASONS.get(event, HoldReason.NONE)
        target, self.goto_target = (self.goto_target, None) if event == E.GOTO_DONE else (None, self.goto_target)
        if target is None and event == E.ALTITUDE_REACHED:
            target = self.takeoff_goal  # the takeoff target, not where the tolerance was entered
        if target is not None:  # hold at the commanded point, not where the radius was entered
            self.publish_goal(GoalOut(target.position_m, target.yaw_rad))
        else:
            self.publish_goal(GoalOut(None))
        if prev == State.LAND and event != E.FC_MODE_CHANGED:
            # landing aborted by us: take control back from AUTO.LAND (never from a pilot)
            self._request_mode("OFFBOARD")
        elif event == E.ALTITUDE_REACHED and self.start_requested:
            if self.perception_required() and not self.perception_healthy:
                # MIS-1 / VIO-3: TAKEOFF exits to EXECUTING on "VIO healthy + altitude reached";
                # wait here like a perception hold (recovered -> EXECUTING, recovery time -> RTL)
                self.hold_reason = HoldReason.PERCEPTION
                self.message = "takeoff complete: waiting for perception (VIO TRACKING) to start the mission"
                return
            self.fire(E.START_CMD, "takeoff complete, starting mission")

    def _enter_executing(self, prev: State, event: Event) -> None:
        self.hold_reason = HoldReason.NONE
        self.blocked_since_s = None
        mode = self.vehicle.flight_mode if self.vehicle else ""
        outcome, self.resume_outcome = self.resume_outcome, None
        if mode and mode != "OFFBOARD":
            # the FC was taken over (or failed over) while we held: resuming asks for OFFBOARD again
            self._request_mode("OFFBOARD", outcome)
            if self.state != State.EXECUTING:  # the request failed at once
                return
        elif outcome:
            outcome.settle(True, self.message)
        if self.goto_target is not None:
            self.publish_goal(self.goto_target)
            return
        if self.wp_index < 0 or self.wp_index >= len(self.mission.waypoints):
            self.wp_index = 0  # not started yet, or completed: (re)start from the first waypoint
        self._publish_waypoint()

    # ------------------------------------------------------------ inputs

    def on_vehicle(self, st: VehicleState, now_s: float) -> None:
        late_not_missing = self._late_not_missing(st)
        self.vehicle = st
        self.now_s = now_s
        self.vehicle_rx_s = now_s
        if not st.connected:
            self._outage_begins("flight-controller link lost (state/vehicle not connected)")
            return
        if self.pending_restore is not None and self.state == State.IDLE:
            self._rebuild(st)
        if st.armed:
            self.armed_seen = True
        if self.outage and self.fmu_alive and self.planner_alive:
            self._outage_ends(late_not_missing)
        self._watch_fc_mode(st)
        pos = st.position_m.to_array()
        on_ground = st.landed_state == LandedState.ON_GROUND
        if (self.state in (State.TAKEOFF, State.EXECUTING, State.HOLDING) and on_ground and not st.armed
                and self.armed_seen):
            self.fire(E.FC_LANDED, f"the flight controller landed and disarmed on its own "
                                   f"(mode {st.flight_mode or 'unknown'}); mission kept loaded")
        elif self.state == State.TAKEOFF:
            if abs(pos[2] - self.takeoff_altitude_m) < self.cfg.altitude_tolerance_m:
                self.fire(E.ALTITUDE_REACHED, "takeoff altitude reached")
        elif self.state == State.EXECUTING:
            self._progress(pos)
        elif self.state == State.LAND:
            self._landing_on_vehicle(st, pos, on_ground, now_s)

    def on_safety(self, action: int, reason: str = "") -> None:
        """safety/status: act once on a rising recommendation (not on every 1 Hz repeat, so the
        operator can command after acknowledging it)."""
        prev, self.safety_action = self.safety_action, action
        if action <= prev:
            return
        name = ACTION_NAMES.get(action, str(action))
        text = f"safety: {name}" + (f" ({reason})" if reason else "")
        self.log("safety_recommendation", action=name, reason=reason, state=self.state.value)
        if action == SafetyStatus.ACTION_EMERGENCY_STOP:
            self.message = f"{text}: executed by the safety service"
            return
        event = SAFETY_REACTIONS.get(action)
        if event is None or self.state == State.IDLE:
            return
        if not self.fire(event, text):
            self.message = text

    def tick(self, now_s: float) -> None:
        """Time-driven checks (call at >= 2 Hz): vehicle-state freshness, perception gating and
        its recovery timer."""
        self.now_s = now_s
        # A late tick means this process stalled (CPU, GIL): samples may be queued, not missing.
        stalled = self.last_tick_s is not None and now_s - self.last_tick_s > self.cfg.vehicle_timeout_s
        self.last_tick_s = now_s
        self._check_vehicle_age(now_s, stalled)
        self._check_restore_deadline(now_s)
        self._gate_perception(now_s)

    def on_link(self, up: bool) -> None:
        if not up:
            self.fire(E.LINK_LOST, "ground-station link lost: holding")

    # ------------------------------------------------------------ helpers

    def in_air(self) -> bool:
        v = self.vehicle
        return v is not None and v.armed and v.landed_state != LandedState.ON_GROUND

    def _position(self) -> np.ndarray:
        return self.vehicle.position_m.to_array() if self.vehicle else np.zeros(3)

    def _waypoint(self, i: int) -> GoalOut:
        wp = self.mission.waypoints[i]
        return GoalOut(np.array([wp.x, wp.y, wp.z]), math.radians(wp.yaw_deg))

    def _publish_waypoint(self) -> None:
        self.blocked_since_s = None             # a new goal: the planner's verdict starts over
        self.publish_goal(self._waypoint(self.wp_index))

    def _progress(self, pos: np.ndarray) -> None:
        if self.goto_target is not None:
            radius = self.goto_target.acceptance_radius_m or self.acceptance_radius_m()
            if np.linalg.norm(self.goto_target.position_m - pos) < radius:
                self.fire(E.GOTO_DONE, "goto reached")
            return
        if self.mission is None or self.wp_index >= len(self.mission.waypoints):
            return
        target = self._waypoint(self.wp_index).position_m
        if np.linalg.norm(target - pos) < self.acceptance_radius_m():
            self.reached_events.append(self.wp_index)
            self.on_waypoint_reached(self.wp_index, pos)
            self.log("waypoint_reached", index=self.wp_index, error_m=round(float(np.linalg.norm(target - pos)), 3))
            self._next_waypoint()

    def _next_waypoint(self) -> None:
        self.wp_index += 1
        self._persist()
        if self.wp_index >= len(self.mission.waypoints):
            if self.cfg.land_on_complete:
                self.fire(E.WAYPOINTS_DONE, "mission complete: landing")
            else:
                self.fire(E.HOLD_CMD, "mission complete: holding")
        else:
            self._publish_waypoint()

    def acceptance_radius_m(self) -> float:
        return self.mission.waypoint_acceptance_radius_m if self.mission else 0.5

    def distance_to_goal_m(self) -> float | None:
        if self.vehicle is None or self.state != State.EXECUTING:
            return None
        pos = self._position()
        if self.goto_target is not None:
            return float(np.linalg.norm(self.goto_target.position_m - pos))
        if self.mission and 0 <= self.wp_index < len(self.mission.waypoints):
            return float(np.linalg.norm(self._waypoint(self.wp_index).position_m - pos))
        return None

    def status(self) -> MissionStatus:
        n = len(self.mission.waypoints) if self.mission else 0
        return MissionStatus(
            mission_id=self.mission.mission_id if self.mission else "",
            state=self.state.value, active_waypoint=self.wp_index if self.mission else -1,
            total_waypoints=n,
            elapsed_time_s=(self.now_s - self.started_s) if self.started_s is not None and self.state != State.IDLE else 0.0,
            perception_healthy=self.perception_healthy, distance_to_goal_m=self.distance_to_goal_m(),
            message=self.message)
