"""What a running mission action (takeoff, land, goto) reports and how it ends: rules over the
mission FSM's state, free of Zenoh, so they are stepped by tests like the FSM itself. main.py
only forwards each Step to the action's goal handle.

- takeoff: feedback (altitude, progress) while TAKEOFF; succeeds holding (or flying on) within
  1 m of the target altitude; aborts when the arming was refused or the FSM is back on the
  ground or landing (not while the arming is still in flight).
- land: feedback (altitude) while LAND; succeeds in IDLE; aborts in any other state (a hold,
  a pilot's takeover).
- goto: feedback (distance, ETA) while EXECUTING it; succeeds when the FSM holds at the target
  (GOTO_DONE); aborts in any other state (a safety hold, a blocked goal, an operator LAND).
- trajectory: flown as a goto to the trajectory's end (the planner follows the trajectory on the
  way): feedback is the planner's TrajectoryStatus; ends like a goto.
A cancel asks HOLD while the vehicle moves (TAKEOFF, EXECUTING, LAND) and ends as canceled.
`forward` hands each running action's Step to its goal handle (feedback, or how it ended).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from aeroperception.schemas import (
    GoToPositionFeedback, GoToPositionResult, LandFeedback, LandResult, SetTrajectoryFeedback, SetTrajectoryResult,
    TakeoffFeedback, TakeoffResult, TrajectoryStatus, Vector3,
)

from .fsm import MissionManager, State
from .requests import Outcome

MOVING = (State.TAKEOFF, State.EXECUTING, State.LAND)    # a cancel asks HOLD in these
RESULTS = {"takeoff": TakeoffResult, "land": LandResult, "goto": GoToPositionResult,
           "trajectory": SetTrajectoryResult}
TAKEOFF_DONE_M = 1.0                                       # within this of the target altitude: done


@dataclass
class Step:
    """One tick of a running action: a feedback message, or the result that ends it."""

    feedback: Any = None
    result: Any = None
    succeeded: bool = False


@dataclass
class ActionRun:
    """One accepted goal of `kind` ("takeoff", "land", "goto", "trajectory"); `outcome` is the
    takeoff's arming answer (None for the others); `status` the planner's latest TrajectoryStatus
    (a trajectory's feedback)."""

    kind: str
    goal: Any
    outcome: Outcome | None = None
    status: Callable[[], TrajectoryStatus | None] | None = None

    def step(self, mgr: MissionManager) -> Step | None:
        """Feedback or the end of this action now, by the FSM's state; None: nothing to say."""
        return getattr(self, f"_{self.kind}")(mgr, mgr.state, _position(mgr))

    def cancel(self, mgr: MissionManager) -> Step:
        """The operator cancelled: hold if the vehicle moves, end as canceled."""
        if mgr.state in MOVING:
            mgr.command("HOLD")
        return Step(result=RESULTS[self.kind](success=False, message=f"cancelled; now {mgr.state.value}"))

    def _takeoff(self, mgr: MissionManager, s: State, pos: Vector3) -> Step | None:
        target = self.goal.target_altitude_m
        if self.outcome is not None and self.outcome.failed:
            return Step(result=TakeoffResult(success=False, message=self.outcome.result[1], final_altitude_m=pos.z))
        if s == State.TAKEOFF:
            return Step(feedback=TakeoffFeedback(current_altitude_m=pos.z,
                                                 progress_percent=max(0.0, min(100.0, 100 * pos.z / target))))
        if s in (State.HOLDING, State.EXECUTING) and abs(pos.z - target) < TAKEOFF_DONE_M:
            return Step(result=TakeoffResult(success=True, message="altitude reached", final_altitude_m=pos.z),
                        succeeded=True)
        if s in (State.IDLE, State.LAND) and not mgr.takeoff_pending:  # not while arming
            return Step(result=TakeoffResult(success=False, message=mgr.message, final_altitude_m=pos.z))
        return None

    def _land(self, mgr: MissionManager, s: State, pos: Vector3) -> Step:
        if s == State.LAND:
            return Step(feedback=LandFeedback(altitude_agl_m=pos.z))
        if s == State.IDLE:
            return Step(result=LandResult(success=True, message="landed", final_position_m=pos), succeeded=True)
        return Step(result=LandResult(success=False, message=mgr.message, final_position_m=pos))

    def _goto(self, mgr: MissionManager, s: State, pos: Vector3) -> Step:
        if s == State.EXECUTING and mgr.goto_target is not None:
            d = mgr.distance_to_goal_m() or 0.0
            speed = float(np.linalg.norm(mgr.vehicle.velocity_mps.to_array()))
            return Step(feedback=GoToPositionFeedback(distance_remaining_m=d, eta_s=d / max(0.1, speed)))
        if s == State.HOLDING and mgr.goto_target is None:
            return Step(result=GoToPositionResult(success=True, message="reached", final_position_m=pos),
                        succeeded=True)
        return Step(result=GoToPositionResult(success=False, message=mgr.message, final_position_m=pos))


    def _trajectory(self, mgr: MissionManager, s: State, pos: Vector3) -> Step:
        if s == State.EXECUTING and mgr.goto_target is not None:
            return Step(feedback=SetTrajectoryFeedback(status=(self.status() if self.status else None)
                                                       or TrajectoryStatus()))
        if s == State.HOLDING and mgr.goto_target is None:
            return Step(result=SetTrajectoryResult(success=True, message="trajectory flown",
                                                   completion_status=TrajectoryStatus.STATUS_COMPLETED), succeeded=True)
        return Step(result=SetTrajectoryResult(success=False, message=mgr.message,
                                               completion_status=TrajectoryStatus.STATUS_ABORTED))


def _position(mgr: MissionManager) -> Vector3:
    return mgr.vehicle.position_m if mgr.vehicle else Vector3()


def forward(actions: list[tuple[ActionRun, Any]], mgr: MissionManager) -> None:
    """Each running action's Step to its goal handle (runtime/actions.GoalHandle: active,
    cancel_requested, feedback / succeed / abort / canceled); an ended one leaves `actions`."""
    for act, h in list(actions):
        step = None if not h.active else act.cancel(mgr) if h.cancel_requested else act.step(mgr)
        if step is None:
            if not h.active:
                actions.remove((act, h))
        elif step.result is None:
            h.feedback(step.feedback)
        elif h.cancel_requested:
            h.canceled(step.result)
        elif step.succeeded:
            h.succeed(step.result)
        else:
            h.abort(step.result)
