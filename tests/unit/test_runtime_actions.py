"""Actions over a real router: goal, feedback, result; rejected and invalid goals; cancel (and its
refusal); a result queried after the fact."""
from __future__ import annotations

import time

import msgpack
import pytest

from aerotest import wait_until

from aeroperception.schemas import (
    GoalReply, GoalStatus, ResultRequest, ActionResult, TakeoffFeedback,
    TakeoffGoal, TakeoffResult, CancelReply, decode,
)
from aeroperception.services.runtime import (
    ActionClient, ActionServer, CallError,
)
from aeroperception.services.runtime.node import call


class _Takeoff:
    """A tiny action server: rejects goals above 100 m, records accepted goals."""

    def __init__(self, node):
        self.handles = []
        self.cancel_asked = []
        self.server = ActionServer(node, "test/action/takeoff", TakeoffGoal, TakeoffResult,
                                   self.on_goal, self.on_cancel)

    def on_goal(self, h):
        if h.goal.target_altitude_m > 100:
            return "target altitude above the 100 m ceiling"
        self.handles.append(h)
        return None

    def on_cancel(self, h):
        self.cancel_asked.append(h.goal_id)
        return True


def _action_pair(make_node):
    srv_node, cli_node = make_node("mission_fake"), make_node("gcs_fake")
    server = _Takeoff(srv_node)
    client = ActionClient(cli_node.session, "test/action/takeoff", TakeoffGoal)

    def ready():
        try:
            call(cli_node.session, "test/action/takeoff/result", ResultRequest(goal_id="x"), ActionResult, 1.0)
            return True
        except CallError:
            return False

    wait_until(ready, 10, "the action server's queryables")
    return srv_node, server, client


def _feed_until(handle, got, fb, what="feedback"):
    wait_until(lambda: handle.feedback(fb) or got, 10, what)


@pytest.mark.timeout(60)
def test_action_goal_feedback_result(make_node):
    srv_node, server, client = _action_pair(make_node)
    feedback = []
    reply = client.send_goal(TakeoffGoal(target_altitude_m=10.0), feedback.append)
    assert isinstance(reply, GoalReply) and reply.accepted and reply.goal_id
    assert reply.status == GoalStatus.ACCEPTED
    h = server.handles[0]
    assert h.goal_id == reply.goal_id and h.goal.target_altitude_m == 10.0
    _feed_until(h, feedback, TakeoffFeedback(current_altitude_m=4.0, progress_percent=40.0))
    fb = feedback[0]
    assert fb.goal_id == reply.goal_id and fb.action == "takeoff" and fb.status == GoalStatus.EXECUTING
    assert fb.unwrap().current_altitude_m == 4.0
    h.succeed(TakeoffResult(success=True, message="reached", final_altitude_m=10.1))
    res = client.result(reply.goal_id, timeout_s=5.0)
    assert res.status == GoalStatus.SUCCEEDED and res.success and res.message == "reached"
    assert res.unwrap().final_altitude_m == 10.1 and isinstance(res.unwrap(), TakeoffResult)
    assert not h.active and server.server.active_goals() == []
    h.abort(TakeoffResult(message="late"))  # finishing twice is ignored
    assert server.server.results[reply.goal_id].status == GoalStatus.SUCCEEDED
    client.close()


@pytest.mark.timeout(60)
def test_action_rejected_and_invalid_goals(make_node):
    srv_node, server, client = _action_pair(make_node)
    reply = client.send_goal(TakeoffGoal(target_altitude_m=500.0))
    assert not reply.accepted and reply.status == GoalStatus.REJECTED
    assert "ceiling" in reply.message and reply.goal_id == ""
    assert server.handles == []
    # A goal that fails validation (negative altitude, sent as a raw map) is refused, not fatal.
    bad = list(client.session.get("test/action/takeoff/goal",
                                  payload=msgpack.packb({"target_altitude_m": -3.0}), timeout=2.0))
    r = decode(bad[0].ok.payload.to_bytes(), GoalReply)
    assert not r.success and "invalid request" in r.message
    assert srv_node.bad_input["test/action/takeoff/goal"] == 1
    client.close()


@pytest.mark.timeout(60)
def test_action_cancel(make_node):
    srv_node, server, client = _action_pair(make_node)
    feedback = []
    reply = client.send_goal(TakeoffGoal(target_altitude_m=20.0), feedback.append)
    h = server.handles[0]
    c = client.cancel(reply.goal_id)
    assert isinstance(c, CancelReply) and c.success and c.status == GoalStatus.CANCELING
    assert server.cancel_asked == [reply.goal_id] and h.cancel_requested
    _feed_until(h, feedback, TakeoffFeedback(current_altitude_m=2.0))
    assert feedback[-1].status == GoalStatus.CANCELING
    h.canceled(TakeoffResult(success=False, message="cancelled by operator", final_altitude_m=2.0))
    res = client.result(reply.goal_id, timeout_s=5.0)
    assert res.status == GoalStatus.CANCELED and not res.success
    again = client.cancel(reply.goal_id)
    assert not again.success and "already finished" in again.message
    unknown = client.cancel("no-such-goal")
    assert not unknown.success and "unknown goal" in unknown.message
    client.close()


@pytest.mark.timeout(60)
def test_action_cancel_refused_by_server(make_node):
    srv_node, server, client = _action_pair(make_node)
    server.server.on_cancel = lambda h: False
    reply = client.send_goal(TakeoffGoal(target_altitude_m=20.0))
    c = client.cancel(reply.goal_id)
    assert not c.success and "cannot be cancelled" in c.message
    assert server.handles[0].active
    client.close()


@pytest.mark.timeout(60)
def test_action_result_queried_after_the_fact(make_node):
    srv_node, server, client = _action_pair(make_node)
    reply = client.send_goal(TakeoffGoal(target_altitude_m=5.0))
    client.close()  # nobody listens while the goal finishes
    running = call(srv_node.session, "test/action/takeoff/result", ResultRequest(goal_id=reply.goal_id),
                   ActionResult)
    assert not running.success and running.status == GoalStatus.ACCEPTED and "still running" in running.message
    server.handles[0].abort(TakeoffResult(success=False, message="motor fault"))
    late = ActionClient(make_node("late_gcs").session, "test/action/takeoff")
    t0 = time.monotonic()
    res = late.result(reply.goal_id, timeout_s=5.0)  # missed the publication: falls back to the query
    assert time.monotonic() - t0 < 3.0
    assert res.status == GoalStatus.ABORTED and res.message == "motor fault"
    unknown = call(srv_node.session, "test/action/takeoff/result", ResultRequest(goal_id="nope"), ActionResult)
    assert unknown.status == GoalStatus.UNKNOWN and "unknown goal" in unknown.message
    with pytest.raises(CallError, match="no result"):
        late.result("nope", timeout_s=1.0)
    late.close()
