"""The action pattern of ARCHITECTURE §3, implemented once (server and client).

For an action at `<area>/action/<name>`:
  <base>/goal      queryable: Goal -> GoalReply (accepted + goal_id, or rejected + reason)
  <base>/cancel    queryable: CancelRequest -> CancelReply
  <base>/feedback  publication: ActionFeedback (goal_id + the action's Feedback)
  <base>/result    publication of ActionResult when a goal ends, and a queryable
                   (ResultRequest -> ActionResult) so a client that connected late still gets it.

The server does not run goals in threads of its own: the service accepts a goal into its own
state machine and finishes it from its own loop (handle.feedback / succeed / abort / canceled).
That keeps all goal logic on the service's single-threaded executor.
"""
from __future__ import annotations

import threading
import time
import uuid
from collections import OrderedDict
from typing import Callable

import zenoh

from aeroperception.schemas import (
    ActionFeedback, ActionResult, CancelReply, CancelRequest, GoalReply, GoalStatus, Message,
    ResultRequest, SchemaError, decode, encode,
)
from aeroperception.schemas.services import Reply

from .node import CallError, Node, call, encoding_for


class GoalHandle:
    """One accepted goal as the service sees it."""

    def __init__(self, server: "ActionServer", goal_id: str, goal: Message):
        self.server = server
        self.goal_id = goal_id
        self.goal = goal
        self.status = GoalStatus.ACCEPTED
        self.cancel_requested = False

    @property
    def active(self) -> bool:
        return self.status not in GoalStatus.TERMINAL

    def feedback(self, fb: Message) -> None:
        if self.active:
            self.status = GoalStatus.CANCELING if self.cancel_requested else GoalStatus.EXECUTING
            self.server._feedback_pub.publish(ActionFeedback.wrap(
                self.goal_id, fb, action=self.server.name, status=self.status,
                header=self.server.node.header()))

    def succeed(self, result: Reply) -> None:
        self._finish(GoalStatus.SUCCEEDED, result)

    def abort(self, result: Reply) -> None:
        self._finish(GoalStatus.ABORTED, result)

    def canceled(self, result: Reply) -> None:
        self._finish(GoalStatus.CANCELED, result)

    def _finish(self, status: int, result: Reply) -> None:
        if not self.active:
            return
        self.status = status
        self.server._finish(self, result)


class ActionServer:
    """Serve one action. `on_goal(handle) -> None | str` accepts (None) or rejects (reason);
    `on_cancel(handle) -> bool` says whether cancelling is possible (the service then ends the
    goal with handle.canceled(...) when it has stopped)."""

    KEEP_RESULTS = 64

    def __init__(self, node: Node, base_key: str, goal_cls: type[Message], result_cls: type[Reply],
                 on_goal: Callable[[GoalHandle], str | None],
                 on_cancel: Callable[[GoalHandle], bool] = lambda h: True):
        self.node = node
        self.base = base_key
        self.name = base_key.rsplit("/", 1)[-1]
        self.result_cls = result_cls
        self.on_goal = on_goal
        self.on_cancel = on_cancel
        self.goals: dict[str, GoalHandle] = {}
        self.results: OrderedDict[str, ActionResult] = OrderedDict()
        self._feedback_pub = node.publisher(f"{base_key}/feedback", ActionFeedback)
        self._result_pub = node.publisher(f"{base_key}/result", ActionResult)
        node.serve(f"{base_key}/goal", goal_cls, GoalReply, self._goal)
        node.serve(f"{base_key}/cancel", CancelRequest, CancelReply, self._cancel)
        node.serve(f"{base_key}/result", ResultRequest, ActionResult, self._result_query)

    def active_goals(self) -> list[GoalHandle]:
        return [h for h in self.goals.values() if h.active]

    def _goal(self, goal: Message) -> GoalReply:
        handle = GoalHandle(self, uuid.uuid4().hex[:16], goal)
        reason = self.on_goal(handle)
        if reason is not None:
            self.node.log.info("goal_rejected", action=self.name, reason=reason)
            return GoalReply(success=False, message=reason, status=GoalStatus.REJECTED)
        self.goals[handle.goal_id] = handle
        self.node.log.info("goal_accepted", action=self.name, goal_id=handle.goal_id)
        return GoalReply(success=True, message="accepted", goal_id=handle.goal_id, status=handle.status)

    def _cancel(self, req: CancelRequest) -> CancelReply:
        h = self.goals.get(req.goal_id)
        if h is None:
            return CancelReply(success=False, message=f"unknown goal {req.goal_id!r}", goal_id=req.goal_id)
        if not h.active:
            return CancelReply(success=False, message="goal already finished", goal_id=h.goal_id, status=h.status)
        if not self.on_cancel(h):
            return CancelReply(success=False, message="goal cannot be cancelled now", goal_id=h.goal_id,
                               status=h.status)
        h.cancel_requested = True
        if h.active:
            h.status = GoalStatus.CANCELING
        return CancelReply(success=True, message="cancelling", goal_id=h.goal_id, status=h.status)

    def _result_query(self, req: ResultRequest) -> ActionResult:
        res = self.results.get(req.goal_id)
        if res is not None:
            return res
        h = self.goals.get(req.goal_id)
        return ActionResult(success=False, goal_id=req.goal_id, action=self.name,
                            status=h.status if h else GoalStatus.UNKNOWN,
                            message="goal still running" if h else f"unknown goal {req.goal_id!r}")

    def _finish(self, h: GoalHandle, result: Reply) -> None:
        env = ActionResult.wrap(h.goal_id, result, h.status, action=self.name, header=self.node.header())
        self.results[h.goal_id] = env
        while len(self.results) > self.KEEP_RESULTS:
            old, _ = self.results.popitem(last=False)
            self.goals.pop(old, None)
        self._result_pub.publish(env)
        self.node.log.info("goal_finished", action=self.name, goal_id=h.goal_id,
                           status=GoalStatus.name(h.status), message=result.message)


class ActionClient:
    """Send a goal, follow its feedback, wait for (or query) its result, cancel it.
    Works on any session (services' Node.session or a CLI's client session)."""

    def __init__(self, session: zenoh.Session, base_key: str, goal_cls: type[Message] | None = None):
        self.session = session
        self.base = base_key
        self.goal_cls = goal_cls
        self._results: dict[str, ActionResult] = {}
        self._feedback_cbs: dict[str, Callable[[ActionFeedback], None]] = {}
        self._cv = threading.Condition()
        self._subs = [
            session.declare_subscriber(f"{base_key}/result", self._on_result),
            session.declare_subscriber(f"{base_key}/feedback", self._on_feedback),
        ]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()

    def _on_result(self, sample: zenoh.Sample) -> None:
        try:
            res = decode(sample.payload.to_bytes(), ActionResult)
        except SchemaError:
            return
        with self._cv:
            self._results[res.goal_id] = res
            self._cv.notify_all()

    def _on_feedback(self, sample: zenoh.Sample) -> None:
        try:
            fb = decode(sample.payload.to_bytes(), ActionFeedback)
        except SchemaError:
            return
        cb = self._feedback_cbs.get(fb.goal_id)
        if cb:
            cb(fb)

    def send_goal(self, goal: Message, feedback_cb: Callable[[ActionFeedback], None] | None = None,
                  timeout_s: float = 5.0) -> GoalReply:
        reply = call(self.session, f"{self.base}/goal", goal, GoalReply, timeout_s)
        if reply.success and feedback_cb:
            self._feedback_cbs[reply.goal_id] = feedback_cb
        return reply

    def result(self, goal_id: str, timeout_s: float) -> ActionResult:
        """Wait for the goal's result; falls back to querying it (covers a missed publication)."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._cv:
                if goal_id in self._results:
                    return self._results[goal_id]
                self._cv.wait(min(0.5, max(0.0, deadline - time.monotonic())))
                if goal_id in self._results:
                    return self._results[goal_id]
            try:
                res = call(self.session, f"{self.base}/result", ResultRequest(goal_id=goal_id), ActionResult, 1.0)
                if res.status in GoalStatus.TERMINAL:
                    return res
            except CallError:
                pass
            if time.monotonic() >= deadline:
                raise CallError(f"{self.base}: no result for goal {goal_id} within {timeout_s:.1f} s")

    def cancel(self, goal_id: str, timeout_s: float = 2.0) -> CancelReply:
        return call(self.session, f"{self.base}/cancel", CancelRequest(goal_id=goal_id), CancelReply, timeout_s)


__all__ = ["ActionServer", "ActionClient", "GoalHandle", "encoding_for", "encode"]
