"""What a running takeoff / land / goto action reports and how it ends
(services/mission/actions.py), stepped over the real FSM without Zenoh."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.schemas import (
    GoToPositionFeedback, LandedState, LandFeedback, LandGoal, SafetyStatus, TakeoffFeedback,
    TakeoffGoal,
)
from aeroperception.services.mission.actions import ActionRun, forward
from aeroperception.services.mission.fsm import State
from mission_rig import FakeBridge, Rig, flying, vehicle


def test_takeoff_reports_its_climb_then_succeeds_at_the_target_altitude():
    rig = Rig()
    rig.to_idle()
    outcome = rig.outcome()
    assert rig.mgr.takeoff(4.0, outcome)[0]
    run = ActionRun("takeoff", TakeoffGoal(target_altitude_m=4.0), outcome)
    rig.feed(vehicle(z=2.0, armed=True, landed=LandedState.IN_AIR))

    step = run.step(rig.mgr)
    assert isinstance(step.feedback, TakeoffFeedback) and step.feedback.progress_percent == pytest.approx(50.0)
    rig.feed(flying(z=4.0))
    step = run.step(rig.mgr)
    assert rig.mgr.state == State.HOLDING
    assert step.succeeded and step.result.success and step.result.final_altitude_m == pytest.approx(4.0)


def test_takeoff_whose_arming_is_refused_ends_with_the_refusal():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.bridge.fail[("arm", True)] = "preflight checks failed"
    outcome = rig.outcome()
    assert rig.mgr.takeoff(4.0, outcome)[0]
    run = ActionRun("takeoff", TakeoffGoal(target_altitude_m=4.0), outcome)
    assert run.step(rig.mgr) is None                  # arming in flight: nothing to say yet

    rig.bridge.answer_pending()
    step = run.step(rig.mgr)
    assert not step.succeeded and step.result.message == "arming failed: preflight checks failed"


def test_land_reports_its_altitude_then_succeeds_on_the_ground():
    rig = Rig()
    rig.to_executing()
    assert rig.mgr.land(None)[0]
    run = ActionRun("land", LandGoal())
    rig.feed(flying(z=3.0))
    step = run.step(rig.mgr)
    assert isinstance(step.feedback, LandFeedback) and step.feedback.altitude_agl_m == pytest.approx(3.0)

    rig.feed(vehicle(armed=False))
    step = run.step(rig.mgr)
    assert rig.mgr.state == State.IDLE and step.succeeded and step.result.message == "landed"


def test_goto_reports_the_distance_left_then_succeeds_holding_at_the_target():
    rig = Rig()
    rig.to_holding()
    assert rig.mgr.goto(np.array([6.0, 0.0, 5.0]), None)[0]
    run = ActionRun("goto", None)
    rig.feed(flying(x=2.0))
    step = run.step(rig.mgr)
    assert isinstance(step.feedback, GoToPositionFeedback) and step.feedback.distance_remaining_m == pytest.approx(4.0)

    rig.feed(flying(x=6.0))
    step = run.step(rig.mgr)
    assert rig.mgr.state == State.HOLDING and step.succeeded and step.result.message == "reached"


def test_goto_interrupted_by_a_safety_hold_ends_with_the_reason():
    rig = Rig()
    rig.to_holding()
    assert rig.mgr.goto(np.array([6.0, 0.0, 5.0]), None)[0]
    rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "geofence")
    step = ActionRun("goto", None).step(rig.mgr)
    assert not step.succeeded and "safety: HOLD (geofence)" in step.result.message


def test_a_cancel_holds_a_moving_vehicle_and_ends_as_cancelled():
    rig = Rig()
    rig.to_holding()
    assert rig.mgr.goto(np.array([6.0, 0.0, 5.0]), None)[0]
    step = ActionRun("goto", None).cancel(rig.mgr)
    assert rig.mgr.state == State.HOLDING
    assert not step.result.success and step.result.message == "cancelled; now HOLDING"


class Handle:
    """What forward() drives: a GoalHandle's surface, recording what it was told."""

    def __init__(self, cancel_requested=False):
        self.active, self.cancel_requested, self.told = True, cancel_requested, []

    def feedback(self, fb):
        self.told.append(("feedback", fb))

    def _end(self, how, result):
        self.told.append((how, result))
        self.active = False

    def succeed(self, r):
        self._end("succeeded", r)

    def abort(self, r):
        self._end("aborted", r)

    def canceled(self, r):
        self._end("canceled", r)


def test_forward_hands_feedback_then_the_end_to_the_goal_handle_and_drops_it_next_tick():
    rig = Rig()
    rig.to_executing()
    assert rig.mgr.land(None)[0]
    h = Handle()
    actions = [(ActionRun("land", LandGoal()), h)]
    rig.feed(flying(z=3.0))
    forward(actions, rig.mgr)
    assert [how for how, _ in h.told] == ["feedback"] and isinstance(h.told[0][1], LandFeedback)
    rig.feed(vehicle(armed=False))
    forward(actions, rig.mgr)
    assert h.told[-1][0] == "succeeded" and h.told[-1][1].message == "landed" and actions
    forward(actions, rig.mgr)                           # ended: no longer stepped
    assert actions == []


def test_forward_ends_a_cancelled_goal_as_canceled_and_a_failed_one_as_aborted():
    rig = Rig()
    rig.to_holding()
    assert rig.mgr.goto(np.array([6.0, 0.0, 5.0]), None)[0]
    cancelled = Handle(cancel_requested=True)
    forward([(ActionRun("goto", None), cancelled)], rig.mgr)      # a cancel asks HOLD
    assert rig.mgr.state == State.HOLDING and cancelled.told[-1][0] == "canceled"
    assert cancelled.told[-1][1].message == "cancelled; now HOLDING"
    rig = Rig()
    rig.to_holding()
    assert rig.mgr.goto(np.array([6.0, 0.0, 5.0]), None)[0]
    rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "geofence")
    failed = Handle()
    forward([(ActionRun("goto", None), failed)], rig.mgr)
    assert failed.told[-1][0] == "aborted" and "safety: HOLD (geofence)" in failed.told[-1][1].message
