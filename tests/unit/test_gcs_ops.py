"""The operations object: each operation answers one Outcome; a mode or a mission start made of
several stack calls chains them (in order while they succeed, or the next only after a refusal),
and a call that got no answer is a failure (FAILED), not a refusal (DENIED)."""
from __future__ import annotations

from aeroperception.schemas import MissionStatus, Reply
from aeroperception.schemas.system import ParamDescriptor
from aeroperception.services.gcs.mission_progress import Progress
from aeroperception.services.gcs.ops import Outcome, StackOps, first_of, in_order
from aeroperception.services.gcs.params import ParamTable
from aeroperception.services.gcs.telemetry import TelemetryState
from aeroperception.services.runtime import CallError
from gcs_support import HOME, FakeStack, Log


def stack_ops(mission: MissionStatus | None = None):
    stack, outcomes = FakeStack(), []
    table = ParamTable(["planner"], aliases=())
    table.update_service("planner", [ParamDescriptor(name="max_velocity_mps", value=2.0, default=2.0)])
    ops = StackOps(stack, 1.0, table, TelemetryState(HOME, mission=mission), Progress(), Log())
    return ops, stack, outcomes


def test_outcome_of_a_reply_or_of_no_reply():
    assert Outcome.of(Reply(success=True, message="ok")) == Outcome(True, "ok")
    assert Outcome.of(Reply(success=False, message="no")) == Outcome(False, "no")
    assert Outcome.of(CallError("timeout calling fmu/srv/arm")) == Outcome(False, "timeout calling fmu/srv/arm",
                                                                           failed=True)


def test_in_order_stops_at_the_first_refusal_first_of_at_the_first_success():
    ran, got = [], []

    def step(name, outcome):
        return lambda done: (ran.append(name), done(outcome))

    in_order([step("a", Outcome(True)), step("b", Outcome(False, "no")), step("c", Outcome(True))], got.append)
    assert ran == ["a", "b"] and got == [Outcome(False, "no")]
    ran.clear(), got.clear()
    first_of([step("a", Outcome(False, "no")), step("b", Outcome(True, "yes")), step("c", Outcome(True))], got.append)
    assert ran == ["a", "b"] and got == [Outcome(True, "yes")]
    ran.clear(), got.clear()
    first_of([step("a", Outcome(False, "no")), step("b", Outcome(False, "nope", failed=True))], got.append)
    assert got == [Outcome(False, "nope", failed=True)]


def test_hold_goes_through_the_mission_manager_else_the_flight_controller():
    ops, stack, outcomes = stack_ops()
    ops.set_mode("HOLD", outcomes.append)
    assert stack.asked() == [("mission/srv/command", "HOLD")]
    stack.answer(Reply(success=True, message="holding"))
    assert outcomes == [Outcome(True, "holding")] and len(stack.calls) == 1
    ops.set_mode("LAND", outcomes.append)
    stack.answer(Reply(success=False, message="not flying a mission"))      # on the ground: the FC decides
    assert stack.asked()[-1] == ("fmu/srv/set_mode", "LAND")
    stack.answer(CallError("timeout calling fmu/srv/set_mode"))
    assert outcomes[-1] == Outcome(False, "timeout calling fmu/srv/set_mode", failed=True)
    ops.set_mode("POSCTL", outcomes.append)
    assert stack.asked()[-1] == ("fmu/srv/set_mode", "POSCTL")


def test_mission_start_on_the_ground_takes_off_first_and_stops_at_a_refusal():
    ops, stack, outcomes = stack_ops(MissionStatus(state=MissionStatus.STATE_IDLE))
    ops.mission_start(outcomes.append)
    assert stack.asked() == [("mission/srv/command", "TAKEOFF")]
    stack.answer(Reply(success=True, message="taking off"))
    assert stack.asked()[-1] == ("mission/srv/command", "START") and outcomes == []
    stack.answer(Reply(success=True, message="started"))
    assert outcomes == [Outcome(True, "started")]

    ops.mission_start(outcomes.append)
    stack.answer(Reply(success=False, message="not armable"))
    assert outcomes[-1] == Outcome(False, "not armable") and stack.asked()[-1] == ("mission/srv/command", "TAKEOFF")

    flying, _, _ = stack_ops(MissionStatus(state=MissionStatus.STATE_HOLDING))
    flying.mission_start(outcomes.append)
    assert flying.call.asked() == [("mission/srv/command", "START")]
