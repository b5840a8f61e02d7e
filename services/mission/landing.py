"""Landing: the LAND state's entry (the FC's LAND or RTL, or a landing the planner flies first),
the phases of a LandPlan as the vehicle moves, touchdown and the disarm after it.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

import numpy as np

from aeroperception.schemas import VehicleState

from .goals import GoalOut, LandPhase, LandPlan
from .requests import FcRequest
from .states import Event, State

E = Event
# The events whose LAND is the FC's return-to-launch (RTL) rather than a landing where it is.
RTL_EVENTS = (E.RTL_CMD, E.PERCEPTION_TIMEOUT, E.SAFETY_RTH, E.GOAL_BLOCKED_RTL)


class Landing:
    """LAND: the FC's mode asked for, or a LandPlan flown phase by phase; disarm after touchdown."""

    land_mode: str                      # LAND | RTL: the FC mode this landing ends in
    land_plan: LandPlan | None          # a landing the planner flies before the FC's LAND
    on_ground_since_s: float | None
    disarm_sent: bool

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
        if plan.phase == LandPhase.APPROACH:
            self.publish_goal(GoalOut(np.array([x, y, plan.approach_z_m])))
        elif plan.phase == LandPhase.DESCEND:
            self.publish_goal(GoalOut(np.array([x, y, ground_z + self.cfg.land_handoff_altitude_m]),
                                      max_vertical_speed_mps=plan.descent_rate_mps))
        else:
            self._request_mode(self.land_mode)

    def _land_progress(self, pos: np.ndarray) -> None:
        plan = self.land_plan
        if plan.phase == LandPhase.APPROACH and \
                np.linalg.norm(plan.target_m[:2] - pos[:2]) < self.acceptance_radius_m():
            plan.phase = LandPhase.DESCEND if plan.descent_rate_mps > 0 else LandPhase.FC
        elif plan.phase == LandPhase.DESCEND and \
                pos[2] <= plan.target_m[2] + self.cfg.land_handoff_altitude_m + self.cfg.altitude_tolerance_m:
            plan.phase = LandPhase.FC
        else:
            return
        self.log("land_phase", phase=plan.phase.value, position=[round(float(v), 2) for v in pos])
        self._land_goal()

    def _landing_on_vehicle(self, st: VehicleState, pos: np.ndarray, on_ground: bool, now_s: float) -> None:
        """A vehicle state while LAND: the plan's next phase, LANDED once on the ground and
        disarmed, and our own disarm when the FC stays armed on the ground too long."""
        if self.land_plan is not None and self.land_plan.phase != LandPhase.FC:
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
