"""The 5-state mission FSM of requirement MIS-1 as an explicit transition table, free of Zenoh.

States IDLE, TAKEOFF, EXECUTING, HOLDING, LAND. Everything that happens is an Event; the only
way the state changes is TRANSITIONS[(state, event)]. Side effects (bridge calls, goal
publication) go through the injected Bridge and `publish_goal`, so tests drive the whole FSM
with plain objects. A bridge call that fails is MIS-1's error path: in the air the
vehicle holds (planner keeps streaming), on the ground it goes back to IDLE, reason reported.

Fault policy (ARCHITECTURE §8), every automatic transition reported in `message`:
- The flight controller has the last word. When it leaves the mode we asked for on its own
  (failsafe, RC pilot, another ground station) the mission goes HOLDING with "flight controller
  switched to <mode>", stops commanding motion (hold goal) and never asks for OFFBOARD again by
  itself: only an explicit START (or goto) re-requests OFFBOARD. When it lands and disarms on its
  own while we think we fly, the mission goes IDLE (mission kept).
- fmu outage (state/vehicle stale, fmu's liveliness gone, or the FC link lost): HOLDING; when
  fresh state is back the mission resumes only if `resume_after_outage` (default: stay HOLDING
  until commanded) and the FC is holding or in OFFBOARD, never out of a failsafe RTL/LAND. A stale
  state that comes back with the next stamp in sequence was late, not missing (fmu kept publishing;
  a CPU or transport stall delayed it): that hold resumes by itself under the same conditions.
- Restart: `restore()` with the persisted mission/progress (persisted only while flying, and
  never a completed one); the first vehicle state decides: flying -> HOLDING ("mission
  restarted in flight"), LAND/RTL/HOLD/START accepted; on the ground -> IDLE with the
  interrupted mission still loaded.
- safety/status: a rising recommended_action HOLD / RTH / LAND acts once (SAFETY_REACTIONS);
  the operator may command afterwards. EMERGENCY_STOP is the safety service's own job.
- VIO lost: the perception service (services/perception/logic.py) turns VIO health into
  perception/health's `overall_healthy` (true iff VIO TRACKING). Here (`tick`), when perception
  is required (the mission's `require_vio`, else `require_perception`): unhealthy, or no
  perception/health for `perception_timeout_s`, while EXECUTING -> HOLDING (PERCEPTION_LOST);
  healthy again -> EXECUTING at the same waypoint (PERCEPTION_RECOVERED); not back within
  `perception_recovery_s` -> RTL (PERCEPTION_TIMEOUT). A takeoff waits in HOLDING the same way
  before starting the mission. Parameters, units and defaults: contract.py.

Operator requests answer through an Outcome (settled at once, or when the flight controller
has answered); what a running takeoff/land/goto action reports is actions.py's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum
from typing import Any, Callable, Mapping

import numpy as np

from aeroperception.schemas import LandedState, Mission, MissionStatus, SafetyStatus, VehicleState, parse_mission

from aeroperception.services.lib.safety_names import ACTION_NAMES

from . import contract
from .requests import Bridge, FcRequest, Outcome
from .limits import Limits


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
RTL_EVENTS = (E.RTL_CMD, E.PERCEPTION_TIMEOUT, E.SAFETY_RTH, E.GOAL_BLOCKED_RTL)
BLOCKED_STATES = ("blocked", "unreachable")   # planner/status obstacle_state: no way to the goal
BLOCKED_ACTIONS = ("hold", "skip", "rtl")


_DEFAULT = {p.name: p.default for p in contract.PARAMS}


@dataclass
class Config:
    """The FSM's settings: each is the mission parameter of the same name (its default, unit and
    range are declared once, in contract.PARAMS)."""

    takeoff_altitude_m: float = _DEFAULT["takeoff_altitude_m"]
    altitude_tolerance_m: float = _DEFAULT["altitude_tolerance_m"]
    require_perception: bool = _DEFAULT["require_perception"]
    perception_timeout_s: float = _DEFAULT["perception_timeout_s"]     # no perception/health this long = unhealthy
    perception_recovery_s: float = _DEFAULT["perception_recovery_s"]   # recover within this or RTL
    land_on_complete: bool = _DEFAULT["land_on_complete"]
    disarm_after_landing_s: float = _DEFAULT["disarm_after_landing_s"]
    vehicle_timeout_s: float = _DEFAULT["vehicle_timeout_s"]           # state/vehicle older than this = fmu outage
    resume_after_outage: bool = _DEFAULT["resume_after_outage"]
    restore_timeout_s: float = _DEFAULT["restore_timeout_s"]
    blocked_timeout_s: float = _DEFAULT["blocked_timeout_s"]
    blocked_action: str = _DEFAULT["blocked_action"]                   # hold | skip | rtl
    land_handoff_altitude_m: float = _DEFAULT["land_handoff_altitude_m"]

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> "Config":
        return cls(**{f.name: params[f.name] for f in fields(cls)})


@dataclass
class GoalOut:
    """What the planner should fly to: a position + yaw (ENU), or None = hold here."""

    position_m: np.ndarray | None
    yaw_rad: float | None = None
    acceptance_radius_m: float | None = None  # goto goals carry their own; None: the mission's
    max_speed_mps: float = 0.0                # the planner's caps for this goal (0: its own)
    max_vertical_speed_mps: float = 0.0


@dataclass
class LandPlan:
    """A landing flown by the planner first (LandGoal target / descent rate): to above the target
    (approach), down at the descent rate to land_handoff_altitude_m above it (descend), then the
    flight controller's LAND (fc)."""

    target_m: np.ndarray                      # the landing point: x, y and the ground's z there
    approach_z_m: float
    descent_rate_mps: float = 0.0
    phase: str = "approach"


class MissionManager:
    def __init__(self, bridge: Bridge, publish_goal: Callable[[GoalOut], None],
                 config: Config | None = None, log: Callable[..., None] | None = None,
                 limits: Limits | None = None):
        self.bridge = bridge
        self.publish_goal = publish_goal
        self.cfg = config or Config()
        self.limits = limits or Limits()
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
        self.armed_seen = False                 # armed since entering TAKEOFF (FC_LANDED guard)
        self.perception_healthy = False
        self.perception_rx_s: float | None = None
        self.hold_reason = ""
        self.hold_since_s = 0.0
        self.land_mode = "LAND"
        self.on_ground_since_s: float | None = None
        self.disarm_sent = False
        self.expected_mode: str | None = None   # the FC mode we asked for last
        self.mode_confirmed = False             # ... and the FC has been seen in it
        self.fmu_alive = True
        self.planner_alive = True               # unknown until its token is seen: assume up
        self.outage: str | None = None          # why we are in an fmu outage, None when not
        self.outage_from: State | None = None
        self.outage_stamp_ns = 0                # newest state/vehicle stamp when it went stale (0: other outage)
        self.safety_action = SafetyStatus.ACTION_NONE
        self.rebuild_pending = False            # restored: the first vehicle state rebuilds us
        self.restored_state = "IDLE"            # the state the previous run persisted
        self.resume_outcome: Outcome | None = None  # START's, settled by the OFFBOARD answer
        self.restore_deadline_s: float | None = None
        self.restored_note = ""                 # what restore() dropped (a completed mission)
        self.blocked_since_s: float | None = None   # planner/status blocked/unreachable since (this goal)
        self.message = "ready"
        self.started_s: float | None = None
        self.now_s = 0.0
        self.transitions: list[tuple[State, Event, State]] = []
        self.reached_events: list[int] = []
        self.on_waypoint_reached: Callable[[int, np.ndarray], None] = lambda i, p: None
        self.on_persist: Callable[[dict], None] = lambda snapshot: None

    # ------------------------------------------------------------ FSM core

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

    def _request_mode(self, mode: str, outcome: Outcome | None = None) -> None:
        """Ask the FC for `mode`; `outcome` (if given) is settled by the FC's answer."""
        self.expected_mode, self.mode_confirmed = mode, False
        self._ask_fc(FcRequest(mode, outcome, "mode"))

    def _ask_fc(self, req: FcRequest) -> None:
        """Send `req` over the bridge; its answer comes back to _on_fc_answer."""
        def answer(ok: bool, message: str) -> None:
            self._on_fc_answer(req, ok, message)
        if req.call in ("arm", "disarm"):
            self.bridge.arm(req.call == "arm", answer)
        else:
            self.bridge.set_mode(req.call, answer)

    def _on_fc_answer(self, req: FcRequest, ok: bool, message: str) -> None:
        """The flight controller answered `req`: settle its outcome; a refused mode is the ERROR
        path (in the air: hold; on the ground: IDLE); a granted arming for TAKEOFF takes off."""
        outcome = req.outcome or Outcome()
        if req.then == "takeoff":
            self.takeoff_pending = False
            if not ok:
                self.start_requested = False
                outcome.settle(False, f"arming failed: {message}")
                self.message = f"arming failed: {message}"
            elif self.fire(E.TAKEOFF_CMD, "taking off"):
                outcome.settle(True, "taking off")
            else:
                outcome.settle(False, f"takeoff not possible in {self.state.value}")
        elif req.then != "mode":
            outcome.settle(ok, message)
        elif ok:
            outcome.settle(True, self.message)
        else:
            what = req.call
            self.log("bridge_failed", call=what, message=message)
            event = E.BRIDGE_FAILED_AIR if self.in_air() else E.BRIDGE_FAILED_GROUND
            if not self.fire(event, f"{what} failed: {message}"):
                self.message = f"{what} failed: {message}"
            outcome.settle(False, f"{what} failed: {message}")

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
        self.hold_reason = {E.PERCEPTION_LOST: "perception", E.LINK_LOST: "link", E.FMU_OUTAGE: "outage",
                            E.FC_MODE_CHANGED: "flight controller", E.RESTARTED_IN_AIR: "restart",
                            E.SAFETY_HOLD: "safety", E.GOAL_BLOCKED: "blocked"}.get(event, "")
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
                self.hold_reason = "perception"
                self.message = "takeoff complete: waiting for perception (VIO TRACKING) to start the mission"
                return
            self.fire(E.START_CMD, "takeoff complete, starting mission")

    def _enter_executing(self, prev: State, event: Event) -> None:
        self.hold_reason = ""
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

    def _enter_land(self, prev: State, event: Event) -> None:
        self.land_mode = "RTL" if event in RTL_EVENTS else "LAND"
        self.on_ground_since_s = None
        self.disarm_sent = False
        if event != E.LAND_CMD:
            self.land_plan = None
        if self.land_plan is not None:
            self._land_goal()
        else:
            self._request_mode(self.land_mode)

    def _land_goal(self) -> None:
        """The goal of the landing plan's phase; the last phase hands over to the FC's LAND."""
        plan = self.land_plan
        x, y, ground_z = plan.target_m
        if plan.phase == "approach":
            self.publish_goal(GoalOut(np.array([x, y, plan.approach_z_m])))
        elif plan.phase == "descend":
            self.publish_goal(GoalOut(np.array([x, y, ground_z + self.cfg.land_handoff_altitude_m]),
                                      max_vertical_speed_mps=plan.descent_rate_mps))
        else:
            self._request_mode(self.land_mode)

    def _land_progress(self, pos: np.ndarray) -> None:
        plan = self.land_plan
        if plan.phase == "approach" and np.linalg.norm(plan.target_m[:2] - pos[:2]) < self.acceptance_radius_m():
            plan.phase = "descend" if plan.descent_rate_mps > 0 else "fc"
        elif plan.phase == "descend" and \
                pos[2] <= plan.target_m[2] + self.cfg.land_handoff_altitude_m + self.cfg.altitude_tolerance_m:
            plan.phase = "fc"
        else:
            return
        self.log("land_phase", phase=plan.phase, position=[round(float(v), 2) for v in pos])
        self._land_goal()

    # ------------------------------------------------------------ persistence and restart

    def snapshot(self) -> dict:
        """What a service restarted mid-flight needs: the mission, its progress and the state we
        were in. On the ground (IDLE) nothing: a new stack after a landed (or finished) flight
        must not come up with the old mission loaded; the mission stays loaded in this process."""
        flying = self.state != State.IDLE and self.mission is not None
        return {"mission_json": self.mission.to_json() if flying else None,
                "wp_index": self.wp_index if flying else -1, "state": self.state.value,
                "start_requested": self.start_requested and flying}

    def _persist(self) -> None:
        self.on_persist(self.snapshot())

    def restore(self, snapshot: dict | None, now_s: float) -> None:
        """Start from what a previous run persisted; the first connected vehicle state decides
        the FSM state (see _rebuild). Until then (at most restore_timeout_s) commands wait."""
        self.now_s = now_s
        self.rebuild_pending = True
        self.restore_deadline_s = now_s + self.cfg.restore_timeout_s
        self.restored_state = (snapshot or {}).get("state", "IDLE")
        self.restored_note = ""
        text = (snapshot or {}).get("mission_json")
        if text:
            try:
                self.mission = parse_mission(text)
                self.wp_index = int(snapshot.get("wp_index", -1))
            except Exception as e:  # noqa: BLE001 - a bad snapshot must not stop a restart
                self.log("restore_failed", error=str(e))
                self.mission, self.wp_index = None, -1
        if self.mission is not None and self.wp_index >= len(self.mission.waypoints):
            # every waypoint was flown (the landing may have been cut short): nothing to resume
            n = len(self.mission.waypoints)
            self.restored_note = f"mission {self.mission.mission_id or '(unnamed)'} was complete ({n}/{n} waypoints)"
            self.mission, self.wp_index = None, -1
        self.message = "restarted: waiting for vehicle state to rebuild the mission state"

    def _rebuild(self, st: VehicleState) -> None:
        self.rebuild_pending = False
        was = self.restored_state
        if self.mission is not None:
            loaded = (f"mission {self.mission.mission_id or '(unnamed)'} loaded at waypoint "
                      f"{max(self.wp_index, 0) + 1}/{len(self.mission.waypoints)}")
        else:
            loaded = f"{self.restored_note}; no mission loaded" if self.restored_note else "no mission loaded"
        if self.in_air():
            mode = st.flight_mode or "unknown mode"
            self.expected_mode = "OFFBOARD" if st.flight_mode == "OFFBOARD" else None
            self.mode_confirmed = self.expected_mode is not None
            self.fire(E.RESTARTED_IN_AIR, f"mission restarted in flight (was {was}, flight controller in {mode}): "
                                          f"holding; {loaded}; LAND, RTL or START to resume")
        else:
            self.message = f"mission restarted on the ground (was {was}); {loaded}"
            self._persist()
        self.log("rebuilt", was=was, state=self.state.value, armed=st.armed,
                 landed_state=st.landed_state, mode=st.flight_mode)

    def restoring(self) -> bool:
        return self.rebuild_pending and self.restore_deadline_s is not None and self.now_s < self.restore_deadline_s

    # ------------------------------------------------------------ inputs

    def load(self, mission: Mission) -> tuple[bool, str]:
        if self.state in (State.EXECUTING, State.TAKEOFF, State.LAND):
            return False, f"cannot load a mission while {self.state.value}; HOLD or land first"
        why = self.limits.check_mission(mission)
        if why:
            self.log("mission_refused", reason=why)
            return False, f"mission refused: {why}"
        self.mission = mission
        self.wp_index = -1
        self.message = f"mission {mission.mission_id or '(unnamed)'} loaded, {len(mission.waypoints)} waypoints"
        self._persist()
        return True, self.message

    def command(self, cmd: str, outcome: Outcome | None = None, waypoint_index: int = -1) -> tuple[bool, str]:
        """Operator command (mission/command). Returns (accepted, message) at once; `outcome` (if
        given) is settled with the final answer: at once, or when the flight controller has
        answered a command that needs it."""
        outcome = outcome or Outcome()
        cmd = cmd.upper()
        if self.restoring():
            return self._refuse(outcome, "restarting: waiting for vehicle state to rebuild the mission state; retry")
        if cmd == "SET_CURRENT":
            return self.set_current(waypoint_index, outcome)
        if cmd == "ARM":
            if self.state != State.IDLE:
                return self._refuse(outcome, f"ARM only in IDLE (now {self.state.value})")
            self._ask_fc(FcRequest("arm", outcome))
            return True, "arming"
        if cmd == "DISARM":
            if self.in_air():
                return self._refuse(outcome, "refusing to disarm in the air; LAND first")
            self._ask_fc(FcRequest("disarm", outcome))
            return True, "disarming"
        if cmd == "TAKEOFF":
            return self.takeoff(None, outcome)
        if cmd == "START":
            return self._start(outcome)
        simple = {"HOLD": E.HOLD_CMD, "LAND": E.LAND_CMD, "RTL": E.RTL_CMD}
        if cmd in simple:
            if not self.fire(simple[cmd], f"operator {cmd}"):
                return self._refuse(outcome, f"{cmd} not possible in {self.state.value}")
            outcome.settle(True, cmd.lower())
            return True, cmd.lower()
        return self._refuse(outcome, f"unknown command {cmd!r}")

    def _start(self, outcome: Outcome) -> tuple[bool, str]:
        """START: fly (or resume) the mission; the outcome is the FC's OFFBOARD answer when the
        resume asks for it, else settled at once."""
        if self.mission is None:
            return self._refuse(outcome, "no mission loaded; LOAD one first")
        if self.state == State.TAKEOFF or self.takeoff_pending:
            self.start_requested = True
            outcome.settle(True, "mission starts when takeoff completes")
            return True, "mission starts when takeoff completes"
        if self.outage and self.state == State.HOLDING:
            return self._refuse(outcome, f"{self.outage}: holding until fresh vehicle state is back")
        self.goto_target = None
        self.resume_outcome = outcome
        fired = self.fire(E.START_CMD, "mission started" if self.wp_index <= 0 else
                          f"mission resumed at waypoint {self.wp_index + 1}/{len(self.mission.waypoints)}")
        self.resume_outcome = None
        if not fired:
            return self._refuse(outcome, f"START not possible in {self.state.value}; TAKEOFF first")
        return outcome.result or (True, self.message)

    def set_current(self, index: int, outcome: Outcome | None = None) -> tuple[bool, str]:
        """Waypoint `index` is the one flown to next (a ground station's MISSION_SET_CURRENT, as
        PX4 jumps): at once while EXECUTING the mission, else where START (or a goto's end) goes on."""
        outcome = outcome or Outcome()
        if self.mission is None:
            return self._refuse(outcome, "no mission loaded; LOAD one first")
        n = len(self.mission.waypoints)
        if not 0 <= index < n:
            return self._refuse(outcome, f"waypoint index {index} out of range: the mission has {n} (0..{n - 1})")
        if self.state == State.LAND:
            return self._refuse(outcome, "not while landing; HOLD first")
        self.wp_index = index
        if self.state == State.EXECUTING and self.goto_target is None:
            self.message = f"jumped to waypoint {index + 1}/{n}"
            self._publish_waypoint()
        else:
            self.message = f"waypoint {index + 1}/{n} is next (START flies there)"
        self.log("set_current", index=index, state=self.state.value)
        self._persist()
        outcome.settle(True, self.message)
        return True, self.message

    @staticmethod
    def _refuse(outcome: Outcome, message: str) -> tuple[bool, str]:
        outcome.settle(False, message)
        return False, message

    def takeoff(self, altitude_m: float | None, outcome: Outcome | None = None,
                climb_rate_mps: float = 0.0) -> tuple[bool, str]:
        """Arm if needed, then TAKEOFF (climbing at most at `climb_rate_mps`, 0: the planner's
        speed). `outcome` is settled by the arming's answer."""
        outcome = outcome or Outcome()
        if self.restoring():
            return self._refuse(outcome, "restarting: waiting for vehicle state; retry")
        if not (math.isfinite(climb_rate_mps) and climb_rate_mps >= 0):
            return self._refuse(outcome, f"field `climb_rate_mps` must be >= 0 (0 = default), got {climb_rate_mps!r}")
        if self.state != State.IDLE:
            return self._refuse(outcome, f"TAKEOFF only from IDLE (now {self.state.value})")
        if self.vehicle is None or not self.vehicle.connected:
            return self._refuse(outcome, "no vehicle state (is fmu connected to the flight controller?)")
        if altitude_m is not None:
            pos = self._position()
            why = self.limits.check_takeoff(altitude_m, pos[0], pos[1])
            if why:
                return self._refuse(outcome, f"takeoff refused: {why}")
        self.takeoff_altitude_m = altitude_m
        self.climb_rate_mps = climb_rate_mps
        self.takeoff_pending = True
        req = FcRequest("arm", outcome, "takeoff")
        if self.vehicle.armed:
            self._on_fc_answer(req, True, "already armed")
        else:
            self._ask_fc(req)
        return True, "taking off"

    def goto(self, position_m: np.ndarray, yaw_rad: float | None,
             acceptance_radius_m: float | None = None, velocity_mps: float = 0.0) -> tuple[bool, str]:
        """Fly to `position_m` at most at `velocity_mps` (0: the planner's speed)."""
        position_m = np.asarray(position_m, float)
        if not (math.isfinite(velocity_mps) and velocity_mps >= 0):
            return False, f"goto refused: field `velocity_mps` must be >= 0 (0 = default), got {velocity_mps!r}"
        why = self.limits.check_goto(*position_m, acceptance_radius_m)
        if why:
            return False, f"goto refused: {why}"
        if self.state not in (State.HOLDING, State.EXECUTING):
            return False, f"GOTO needs the vehicle in the air (HOLDING/EXECUTING), now {self.state.value}"
        if self.outage:
            return False, f"{self.outage}: holding until fresh vehicle state is back"
        self.goto_target = GoalOut(position_m, yaw_rad, acceptance_radius_m, max_speed_mps=velocity_mps)
        self.blocked_since_s = None
        if self.state == State.EXECUTING:
            self.publish_goal(self.goto_target)
        elif not self.fire(E.START_CMD, "goto") or self.state != State.EXECUTING:
            return False, self.message
        return True, "going"

    def land(self, target_m: np.ndarray | None, descent_rate_mps: float = 0.0) -> tuple[bool, str]:
        """LAND, at `target_m` (x, y and the ground's z there; None: here) and/or descending at
        most at `descent_rate_mps` down to land_handoff_altitude_m (then the FC lands)."""
        if not (math.isfinite(descent_rate_mps) and descent_rate_mps >= 0):
            return False, f"field `descent_rate_mps` must be >= 0 (0 = default), got {descent_rate_mps!r}"
        if target_m is None and descent_rate_mps == 0:
            return self.command("LAND")
        if self.restoring() or self.state not in (State.TAKEOFF, State.EXECUTING, State.HOLDING):
            return False, f"LAND not possible in {self.state.value}"
        pos = self._position()
        if target_m is not None:
            target_m = np.asarray(target_m, float)
            why = self.limits.check_goto(target_m[0], target_m[1], pos[2], None)
            if why:
                return False, f"land refused: target_position_m: {why}"
        target = target_m if target_m is not None else np.array([pos[0], pos[1], 0.0])
        self.land_plan = LandPlan(target, float(pos[2]), descent_rate_mps,
                                  "approach" if target_m is not None else "descend")
        where = f" at ({target[0]:.1f}, {target[1]:.1f})" if target_m is not None else ""
        rate = f", descending at {descent_rate_mps:g} m/s" if descent_rate_mps > 0 else ""
        if not self.fire(E.LAND_CMD, f"operator LAND{where}{rate}"):
            self.land_plan = None
            return False, f"LAND not possible in {self.state.value}"
        return True, self.message

    def on_vehicle(self, st: VehicleState, now_s: float) -> None:
        # The state went stale, but the next one carries the next stamp: fmu kept publishing and the
        # samples were only late (a CPU or transport stall between fmu and us), not an fmu outage.
        late_not_missing = bool(self.outage_stamp_ns and st.header.stamp_ns
                                and st.header.stamp_ns - self.outage_stamp_ns < self.cfg.vehicle_timeout_s * 1e9)
        self.vehicle = st
        self.now_s = now_s
        self.vehicle_rx_s = now_s
        if not st.connected:
            self._outage_begins("flight-controller link lost (state/vehicle not connected)")
            return
        if self.rebuild_pending and self.state == State.IDLE:
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
            if self.land_plan is not None and self.land_plan.phase != "fc":
                self._land_progress(pos)
            if not on_ground:
                self.on_ground_since_s = None
            elif self.on_ground_since_s is None:
                self.on_ground_since_s = now_s
            if on_ground and not st.armed:
                self.fire(E.LANDED, "landed and disarmed")
            elif (on_ground and not self.disarm_sent
                  and now_s - self.on_ground_since_s > self.cfg.disarm_after_landing_s):
                self.disarm_sent = True
                self._ask_fc(FcRequest("disarm"))

    def _watch_fc_mode(self, st: VehicleState) -> None:
        """The FC left the mode we asked for without being asked: never fight it. Not when it
        disarms: PX4 then switches to the last mode it can arm in (after a LAND that ends in
        OFFBOARD), which flies nothing and is no takeover."""
        mode = st.flight_mode
        if not mode or self.expected_mode is None or not st.armed:
            return
        landing = self.state == State.LAND and self.expected_mode in ("LAND", "RTL")
        ours = ("LAND", "RTL") if landing else (self.expected_mode,)
        if mode in ours:
            self.mode_confirmed = True
            return
        if not self.mode_confirmed:
            return  # our request is not confirmed yet (heartbeats lag): nothing to judge
        self.expected_mode, self.mode_confirmed = None, False
        reason = f"flight controller switched to {mode}"
        self.log("fc_mode_changed", mode=mode, state=self.state.value)
        if not self.fire(E.FC_MODE_CHANGED, f"{reason}: holding, not commanding motion; START resumes"):
            if self.state == State.HOLDING:
                self.hold_reason = "flight controller"
                self.message = f"{reason}; holding, START resumes"

    def on_fmu_alive(self, alive: bool, now_s: float) -> None:
        """fmu's liveliness token (aero/alive/<vehicle>/fmu) came or went."""
        self.now_s = now_s
        self.fmu_alive = alive
        if not alive:
            self._outage_begins("fmu outage (fmu not alive)")

    def on_planner_alive(self, alive: bool, now_s: float) -> None:
        """The planner's liveliness token came or went (ARCHITECTURE §8: after a planner outage
        the vehicle holds until the mission has re-checked it; fmu brakes meanwhile). The same
        outage path as fmu's: HOLDING, resumed only by START or resume_after_outage."""
        self.now_s = now_s
        self.planner_alive = alive
        if not alive:
            self._outage_begins("planner outage (planner not alive)")
        elif self.outage and self.fmu_alive and self.vehicle is not None \
                and now_s - self.vehicle_rx_s < self.cfg.vehicle_timeout_s:
            self._outage_ends()

    def _outage_begins(self, why: str, stamp_ns: int = 0) -> None:
        if self.outage:
            return
        self.outage, self.outage_from, self.outage_stamp_ns = why, self.state, stamp_ns
        self.log("outage", reason=why, state=self.state.value)
        if not self.fire(E.FMU_OUTAGE, f"{why}: holding"):
            if self.state != State.IDLE:
                self.message = f"{why} ({self.state.value} continues: the flight controller flies on its own)" \
                    if self.state == State.LAND else f"{why}: holding"

    def _outage_ends(self, late_not_missing: bool = False) -> None:
        """`late_not_missing`: the stale state came back without a gap in its stamps (it was late)."""
        was, self.outage, self.outage_stamp_ns = self.outage, None, 0
        self.log("outage_over", reason=was, state=self.state.value, late_not_missing=late_not_missing)
        if self.state != State.HOLDING:
            return
        mode = self.vehicle.flight_mode if self.vehicle else ""
        if ((self.cfg.resume_after_outage or late_not_missing) and self.outage_from == State.EXECUTING
                and self.hold_reason == "outage" and self.mission is not None
                and mode in ("", "OFFBOARD", "HOLD")):
            # never out of a failsafe RTL/LAND the FC chose: only from its hold (or our OFFBOARD)
            self.fire(E.OUTAGE_RESUME, "state/vehicle was late, not missing (no gap in fmu's stamps): resuming"
                      if late_not_missing else "fmu back after an outage: resuming (resume_after_outage)")
        else:
            self.message = "fmu back after an outage: holding until commanded (START resumes)"

    def on_perception(self, healthy: bool, now_s: float) -> None:
        self.perception_healthy = healthy
        self.perception_rx_s = now_s

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
        if (self.vehicle_rx_s is not None and not self.outage and not stalled
                and now_s - self.vehicle_rx_s > self.cfg.vehicle_timeout_s):
            self._outage_begins(f"fmu outage (no state/vehicle for {now_s - self.vehicle_rx_s:.1f} s)",
                                stamp_ns=self.vehicle.header.stamp_ns if self.vehicle else 0)
        if self.rebuild_pending and self.restore_deadline_s is not None and now_s >= self.restore_deadline_s:
            self.restore_deadline_s = None  # stop refusing commands; rebuild still on the first state
            self.message = "restarted: no vehicle state yet (is fmu running?)"
        if self.perception_rx_s is not None and now_s - self.perception_rx_s > self.cfg.perception_timeout_s:
            self.perception_healthy = False
        if not self.perception_required():
            return
        if self.state == State.EXECUTING and not self.perception_healthy:
            self.fire(E.PERCEPTION_LOST, "perception unhealthy: holding")
        elif self.state == State.HOLDING and self.hold_reason == "perception" and not self.outage:
            if self.perception_healthy:
                self.fire(E.PERCEPTION_RECOVERED, "perception recovered: resuming" if self.wp_index >= 0
                          else "perception healthy: starting mission")
            elif now_s - self.hold_since_s > self.cfg.perception_recovery_s:
                self.fire(E.PERCEPTION_TIMEOUT, "perception lost > recovery time: RTL")

    def on_planner(self, obstacle_state: str, message: str, now_s: float) -> None:
        """planner/status: a goal the planner reports blocked or unreachable for blocked_timeout_s
        reaches the mission (never EXECUTING silently for ever): blocked_action hold -> HOLDING
        with the reason (START retries, SET_CURRENT skips, LAND/RTL); skip -> the next waypoint
        (a goto holds); rtl -> RTL. Each reported in `message`."""
        self.now_s = now_s
        if self.state != State.EXECUTING or obstacle_state not in BLOCKED_STATES:
            self.blocked_since_s = None
            return
        if self.blocked_since_s is None:
            self.blocked_since_s = now_s
        held_s = now_s - self.blocked_since_s
        if held_s < self.cfg.blocked_timeout_s:
            return
        self.blocked_since_s = None
        goal = self.goto_target or self._waypoint(self.wp_index)
        x, y, z = goal.position_m
        what = "goto target" if self.goto_target is not None else \
            f"waypoint {self.wp_index + 1}/{len(self.mission.waypoints)}"
        reason = f"{what} ({x:.1f}, {y:.1f}, {z:.1f}) unreachable for {held_s:.0f} s (planner {obstacle_state}: {message})"
        action = self.cfg.blocked_action
        self.log("goal_blocked", goal=what, planner=obstacle_state, reason=message, action=action)
        if action == "rtl":
            self.fire(E.GOAL_BLOCKED_RTL, f"{reason}: returning home (blocked_action rtl)")
        elif action == "skip" and self.goto_target is None:
            self.message = f"skipped {reason}"
            self._next_waypoint()
        else:
            self.fire(E.GOAL_BLOCKED, f"holding: {reason}; START retries, SET_CURRENT skips, LAND/RTL")

    def on_trajectory_refused(self, why: str) -> None:
        """planner/status: the trajectory handed over is refused for what it asks (limits above the
        planner's own, a frame, a generator; a SetTrajectory one against the planner's live limits).
        The planner holds rather than fly it goal by goal: so does the mission, saying why."""
        if self.state == State.EXECUTING:
            self.fire(E.GOAL_BLOCKED, f"holding: {why}; START retries, LAND/RTL")

    def on_link(self, up: bool) -> None:
        if not up:
            self.fire(E.LINK_LOST, "ground-station link lost: holding")

    # ------------------------------------------------------------ helpers

    def perception_required(self) -> bool:
        if self.mission is not None and self.mission.require_vio is not None:
            return self.mission.require_vio
        return self.cfg.require_perception

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
