"""The 5-state mission FSM of seed 000 §5.1 as an explicit transition table, free of Zenoh.

States IDLE, TAKEOFF, EXECUTING, HOLDING, LAND. Everything that happens is an Event; the only
way the state changes is TRANSITIONS[(state, event)]. Side effects (bridge calls, goal
publication) go through the injected Bridge and `publish_goal`, so tests drive the whole FSM
with plain objects. A bridge call that fails is the ERROR path of the seed: in the air the
vehicle holds (planner keeps streaming), on the ground it goes back to IDLE, reason reported.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Callable, Protocol

import numpy as np

from aeroperception.schemas import LandedState, Mission, MissionStatus, VehicleState


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
}


class Bridge(Protocol):
    """The flight-controller calls the mission needs (fmu/srv/* in the running stack).
    `done(success, message)` is called exactly once, later or immediately."""

    def arm(self, arm: bool, done: Callable[[bool, str], None]) -> None: ...

    def set_mode(self, mode: str, done: Callable[[bool, str], None]) -> None: ...


@dataclass
class Config:
    takeoff_altitude_m: float = 3.0
    altitude_tolerance_m: float = 0.3
    require_perception: bool = False
    perception_timeout_s: float = 3.0       # no perception/health for this long = unhealthy
    perception_recovery_s: float = 10.0     # seed 000 §4.1: recover within 10 s or RTL
    land_on_complete: bool = True
    disarm_after_landing_s: float = 5.0     # if the FC has not auto-disarmed by then, disarm


@dataclass
class GoalOut:
    """What the planner should fly to: a position + yaw (ENU), or None = hold here."""

    position_m: np.ndarray | None
    yaw_rad: float | None = None
    acceptance_radius_m: float | None = None  # goto goals carry their own; None: the mission's


class MissionManager:
    def __init__(self, bridge: Bridge, publish_goal: Callable[[GoalOut], None],
                 config: Config | None = None, log: Callable[..., None] | None = None):
        self.bridge = bridge
        self.publish_goal = publish_goal
        self.cfg = config or Config()
        self.log = log or (lambda *a, **k: None)
        self.state = State.IDLE
        self.mission: Mission | None = None
        self.wp_index = -1
        self.start_requested = False
        self.takeoff_pending = False            # arming for a takeoff is in flight
        self.goto_target: GoalOut | None = None
        self.takeoff_altitude_m: float | None = None
        self.vehicle: VehicleState | None = None
        self.perception_healthy = False
        self.perception_rx_s: float | None = None
        self.hold_reason = ""
        self.hold_since_s = 0.0
        self.land_mode = "LAND"
        self.on_ground_since_s: float | None = None
        self.disarm_sent = False
        self.message = "ready"
        self.started_s: float | None = None
        self.now_s = 0.0
        self.transitions: list[tuple[State, Event, State]] = []
        self.reached_events: list[int] = []
        self.on_waypoint_reached: Callable[[int, np.ndarray], None] = lambda i, p: None

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
        return True

    def _enter_idle(self, prev: State, event: Event) -> None:
        self.start_requested = False
        self.goto_target = None
        self.takeoff_altitude_m = None
        self.publish_goal(GoalOut(None))

    def _enter_takeoff(self, prev: State, event: Event) -> None:
        pos = self._position()
        alt = self.takeoff_altitude_m or (self.mission.takeoff_altitude_m if self.mission else self.cfg.takeoff_altitude_m)
        self.takeoff_altitude_m = alt
        self.started_s = self.now_s
        self.publish_goal(GoalOut(np.array([pos[0], pos[1], alt]), self.vehicle.yaw_rad if self.vehicle else None))
        self.bridge.set_mode("OFFBOARD", self._bridge_done("OFFBOARD"))

    def _enter_holding(self, prev: State, event: Event) -> None:
        self.hold_since_s = self.now_s
        self.hold_reason = {E.PERCEPTION_LOST: "perception", E.LINK_LOST: "link"}.get(event, "")
        target, self.goto_target = (self.goto_target, None) if event == E.GOTO_DONE else (None, self.goto_target)
        if target is not None:  # hold at the commanded point, not where the radius was entered
            self.publish_goal(GoalOut(target.position_m, target.yaw_rad))
        else:
            self.publish_goal(GoalOut(None))
        if prev == State.LAND:  # landing aborted: take control back from AUTO.LAND
            self.bridge.set_mode("OFFBOARD", self._bridge_done("OFFBOARD"))
        elif event == E.ALTITUDE_REACHED and self.start_requested:
            self.fire(E.START_CMD, "takeoff complete, starting mission")

    def _enter_executing(self, prev: State, event: Event) -> None:
        self.hold_reason = ""
        if self.goto_target is not None:
            self.publish_goal(self.goto_target)
            return
        if self.wp_index < 0 or self.wp_index >= len(self.mission.waypoints):
            self.wp_index = 0  # not started yet, or completed: (re)start from the first waypoint
        self._publish_waypoint()

    def _enter_land(self, prev: State, event: Event) -> None:
        self.land_mode = "RTL" if event in (E.RTL_CMD, E.PERCEPTION_TIMEOUT) else "LAND"
        self.on_ground_since_s = None
        self.disarm_sent = False
        self.bridge.set_mode(self.land_mode, self._bridge_done(self.land_mode))

    def _bridge_done(self, what: str) -> Callable[[bool, str], None]:
        def done(ok: bool, message: str) -> None:
            if ok:
                return
            self.log("bridge_failed", call=what, message=message)
            event = E.BRIDGE_FAILED_AIR if self.in_air() else E.BRIDGE_FAILED_GROUND
            if not self.fire(event, f"{what} failed: {message}"):
                self.message = f"{what} failed: {message}"
        return done

    # ------------------------------------------------------------ inputs

    def load(self, mission: Mission) -> tuple[bool, str]:
        if self.state in (State.EXECUTING, State.TAKEOFF, State.LAND):
            return False, f"cannot load a mission while {self.state.value}; HOLD or land first"
        self.mission = mission
        self.wp_index = -1
        self.message = f"mission {mission.mission_id or '(unnamed)'} loaded, {len(mission.waypoints)} waypoints"
        return True, self.message

    def command(self, cmd: str, on_result: Callable[[bool, str], None] | None = None) -> tuple[bool, str]:
        """Operator command (mission/command). Returns (accepted, message) at once; commands that
        need the flight controller report their outcome through `on_result` as well."""
        done = on_result or (lambda ok, msg: None)
        cmd = cmd.upper()
        if cmd == "ARM":
            if self.state != State.IDLE:
                return self._refuse(done, f"ARM only in IDLE (now {self.state.value})")
            self.bridge.arm(True, done)
            return True, "arming"
        if cmd == "DISARM":
            if self.in_air():
                return self._refuse(done, "refusing to disarm in the air; LAND first")
            self.bridge.arm(False, done)
            return True, "disarming"
        if cmd == "TAKEOFF":
            return self.takeoff(None, done)
        if cmd == "START":
            if self.mission is None:
                return self._refuse(done, "no mission loaded; LOAD one first")
            if self.state == State.TAKEOFF or self.takeoff_pending:
                self.start_requested = True
                done(True, "mission starts when takeoff completes")
                return True, "mission starts when takeoff completes"
            self.goto_target = None
            if not self.fire(E.START_CMD, "mission started"):
                return self._refuse(done, f"START not possible in {self.state.value}; TAKEOFF first")
            done(True, "mission started")
            return True, "mission started"
        simple = {"HOLD": E.HOLD_CMD, "LAND": E.LAND_CMD, "RTL": E.RTL_CMD}
        if cmd in simple:
            if not self.fire(simple[cmd], f"operator {cmd}"):
                return self._refuse(done, f"{cmd} not possible in {self.state.value}")
            done(True, cmd.lower())
            return True, cmd.lower()
        return self._refuse(done, f"unknown command {cmd!r}")

    def _refuse(self, done, message: str) -> tuple[bool, str]:
        done(False, message)
        return False, message

    def takeoff(self, altitude_m: float | None, done: Callable[[bool, str], None]) -> tuple[bool, str]:
        """Arm if needed, then TAKEOFF. `done` reports the arm/offboard outcome."""
        if self.state != State.IDLE:
            return self._refuse(done, f"TAKEOFF only from IDLE (now {self.state.value})")
        if self.vehicle is None or not self.vehicle.connected:
            return self._refuse(done, "no vehicle state (is fmu connected to the flight controller?)")
        self.takeoff_altitude_m = altitude_m
        self.takeoff_pending = True

        def armed(ok: bool, message: str) -> None:
            self.takeoff_pending = False
            if not ok:
                self.start_requested = False
                done(False, f"arming failed: {message}")
                self.message = f"arming failed: {message}"
                return
            if self.fire(E.TAKEOFF_CMD, "taking off"):
                done(True, "taking off")
            else:
                done(False, f"takeoff not possible in {self.state.value}")

        if self.vehicle.armed:
            armed(True, "already armed")
        else:
            self.bridge.arm(True, armed)
        return True, "taking off"

    def goto(self, position_m: np.ndarray, yaw_rad: float | None,
             acceptance_radius_m: float | None = None) -> tuple[bool, str]:
        if self.state not in (State.HOLDING, State.EXECUTING):
            return False, f"GOTO needs the vehicle in the air (HOLDING/EXECUTING), now {self.state.value}"
        self.goto_target = GoalOut(np.asarray(position_m, float), yaw_rad, acceptance_radius_m)
        if self.state == State.EXECUTING:
            self.publish_goal(self.goto_target)
        else:
            self.fire(E.START_CMD, "goto")
        return True, "going"

    def on_vehicle(self, st: VehicleState, now_s: float) -> None:
        self.vehicle = st
        self.now_s = now_s
        pos = st.position_m.to_array()
        if self.state == State.TAKEOFF:
            if abs(pos[2] - self.takeoff_altitude_m) < self.cfg.altitude_tolerance_m:
                self.fire(E.ALTITUDE_REACHED, "takeoff altitude reached")
        elif self.state == State.EXECUTING:
            self._progress(pos)
        elif self.state == State.LAND:
            on_ground = st.landed_state == LandedState.ON_GROUND
            if not on_ground:
                self.on_ground_since_s = None
            elif self.on_ground_since_s is None:
                self.on_ground_since_s = now_s
            if on_ground and not st.armed:
                self.fire(E.LANDED, "landed and disarmed")
            elif (on_ground and not self.disarm_sent
                  and now_s - self.on_ground_since_s > self.cfg.disarm_after_landing_s):
                self.disarm_sent = True
                self.bridge.arm(False, lambda ok, m: None)

    def on_perception(self, healthy: bool, now_s: float) -> None:
        self.perception_healthy = healthy
        self.perception_rx_s = now_s

    def tick(self, now_s: float) -> None:
        """Time-driven checks (call at >= 2 Hz): perception gating and its recovery timer."""
        self.now_s = now_s
        if self.perception_rx_s is not None and now_s - self.perception_rx_s > self.cfg.perception_timeout_s:
            self.perception_healthy = False
        if not self.perception_required():
            return
        if self.state == State.EXECUTING and not self.perception_healthy:
            self.fire(E.PERCEPTION_LOST, "perception unhealthy: holding")
        elif self.state == State.HOLDING and self.hold_reason == "perception":
            if self.perception_healthy:
                self.fire(E.PERCEPTION_RECOVERED, "perception recovered: resuming")
            elif now_s - self.hold_since_s > self.cfg.perception_recovery_s:
                self.fire(E.PERCEPTION_TIMEOUT, "perception lost > recovery time: RTL")

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
            self.wp_index += 1
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
