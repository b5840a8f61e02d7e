"""Operator requests to the mission FSM: LOAD, the mission/command verbs (ARM, DISARM, TAKEOFF,
START, HOLD, LAND, RTL, SET_CURRENT), and the goals a takeoff, goto or landing action carries.
Each answers at once with (accepted, message), refused with the reason when it cannot be
honoured; an Outcome (if given) is settled with the final answer, at once or when the flight
controller has answered.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.schemas import Mission

from .goals import GoalOut, LandPhase, LandPlan
from .requests import FcRequest, Outcome
from .states import Event as E, State


class OperatorCommands:
    """load / command / set_current / takeoff / goto / land."""

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
                                  LandPhase.APPROACH if target_m is not None else LandPhase.DESCEND)
        where = f" at ({target[0]:.1f}, {target[1]:.1f})" if target_m is not None else ""
        rate = f", descending at {descent_rate_mps:g} m/s" if descent_rate_mps > 0 else ""
        if not self.fire(E.LAND_CMD, f"operator LAND{where}{rate}"):
            self.land_plan = None
            return False, f"LAND not possible in {self.state.value}"
        return True, self.message
