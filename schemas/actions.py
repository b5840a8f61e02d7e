"""Long-running goals (requirement IF-3's actions): per-action Goal/Result/Feedback types and the generic
envelope the runtime's one action implementation uses (ARCHITECTURE §3).

Protocol, for an action at `<area>/action/<name>` (e.g. mission/action/takeoff); ARCHITECTURE §3
fixes the feedback and result keys, the runtime owns the exact goal/cancel key names:
  - goal:     query the goal queryable with the Goal  -> GoalReply (accepted + goal_id)
  - feedback: published on `.../feedback` as ActionFeedback (goal_id, status, feedback map)
  - result:   published on `.../result` as ActionResult, and `.../result` is also a queryable
              taking ResultRequest (the last result for that goal id)
  - cancel:   query the cancel queryable with CancelRequest -> CancelReply

Envelope design: ActionFeedback.feedback / ActionResult.result are plain msgpack maps holding the
action's Feedback / Result struct (with its schema id next to it), not msgspec.Raw or a generic
Struct: the envelope then stays one registered type per role, readable by any msgpack library
(a nested map, not opaque bytes), and works with to_builtins/from_builtins for `aero topic echo`
and `pub`. `wrap()` builds an envelope from a typed message; `unwrap()` validates it back.
GoalReply.success means "accepted" and ActionResult/CancelReply carry success + message like every
other reply, so one client helper checks them all.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import msgspec

from ._base import Header, Message, SchemaError, get_schema, schema, schema_id, to_builtins
from ._checks import check_finite, check_positive, enum_names
from .geometry import Vector3
from .planning import Trajectory, TrajectoryStatus
from .services import Reply

__all__ = [
    "TakeoffGoal", "TakeoffResult", "TakeoffFeedback",
    "LandGoal", "LandResult", "LandFeedback",
    "SetTrajectoryGoal", "SetTrajectoryResult", "SetTrajectoryFeedback",
    "GoToPositionGoal", "GoToPositionResult", "GoToPositionFeedback",
    "GoalStatus", "GoalReply", "CancelRequest", "CancelReply", "ResultRequest",
    "ActionFeedback", "ActionResult", "ActionSpec", "ACTIONS",
]


# ---------------------------------------------------------------- Takeoff


@schema("TakeoffGoal", 1)
class TakeoffGoal(Message, kw_only=True):
    """Climb to `target_altitude_m` above ground; `climb_rate_mps` 0 = the service default."""

    header: Header = msgspec.field(default_factory=Header)
    target_altitude_m: float
    climb_rate_mps: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive("target_altitude_m", self.target_altitude_m)


@schema("TakeoffResult", 1)
class TakeoffResult(Reply, kw_only=True):
    final_altitude_m: float = 0.0


@schema("TakeoffFeedback", 1)
class TakeoffFeedback(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    current_altitude_m: float = 0.0
    progress_percent: float = 0.0


# ---------------------------------------------------------------- Land


@schema("LandGoal", 1)
class LandGoal(Message, kw_only=True):
    """Land here, or at `target_position_m` (ENU) when `land_at_current_position` is False;
    `descent_rate_mps` 0 = the service default."""

    header: Header = msgspec.field(default_factory=Header)
    land_at_current_position: bool = True
    target_position_m: Vector3 = msgspec.field(default_factory=Vector3)
    descent_rate_mps: float = 0.0


@schema("LandResult", 1)
class LandResult(Reply, kw_only=True):
    final_position_m: Vector3 = msgspec.field(default_factory=Vector3)


@schema("LandFeedback", 1)
class LandFeedback(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    altitude_agl_m: float = 0.0
    progress_percent: float = 0.0


# ---------------------------------------------------------------- SetTrajectory


@schema("SetTrajectoryGoal", 1)
class SetTrajectoryGoal(Message, kw_only=True):
    """Fly `trajectory`, replacing the current one (or appended to it when `replace_current` is False)."""

    header: Header = msgspec.field(default_factory=Header)
    trajectory: Trajectory
    replace_current: bool = True


@schema("SetTrajectoryResult", 1)
class SetTrajectoryResult(Reply, kw_only=True):
    """`completion_status` is a TrajectoryStatus.STATUS_* value (COMPLETED, ABORTED, ERROR)."""

    completion_status: int = TrajectoryStatus.STATUS_IDLE


@schema("SetTrajectoryFeedback", 1)
class SetTrajectoryFeedback(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    status: TrajectoryStatus = msgspec.field(default_factory=TrajectoryStatus)


# ---------------------------------------------------------------- GoToPosition


@schema("GoToPositionGoal", 1)
class GoToPositionGoal(Message, kw_only=True):
    """Fly to `position_m` (ENU). `yaw_rad` None (or NaN, as in IF-3's GoToPosition) keeps the current
    heading; `velocity_mps` 0 = the planner's default speed."""

    header: Header = msgspec.field(default_factory=Header)
    position_m: Vector3
    yaw_rad: float | None = None
    velocity_mps: float = 0.0
    acceptance_radius_m: float = 0.5

    def __post_init__(self) -> None:
        super().__post_init__()
        for axis in ("x", "y", "z"):
            check_finite(f"position_m.{axis}", getattr(self.position_m, axis))
        check_positive("acceptance_radius_m", self.acceptance_radius_m)


@schema("GoToPositionResult", 1)
class GoToPositionResult(Reply, kw_only=True):
    final_position_m: Vector3 = msgspec.field(default_factory=Vector3)


@schema("GoToPositionFeedback", 1)
class GoToPositionFeedback(Message, kw_only=True):
    """`eta_s` is None while no estimate exists (vehicle not yet moving)."""

    header: Header = msgspec.field(default_factory=Header)
    distance_remaining_m: float = 0.0
    eta_s: float | None = None


# ---------------------------------------------------------------- generic protocol


class GoalStatus:
    """Goal lifecycle values (ROS action_msgs/GoalStatus numbering, plus REJECTED)."""

    UNKNOWN = 0
    ACCEPTED = 1
    EXECUTING = 2
    CANCELING = 3
    SUCCEEDED = 4
    CANCELED = 5
    ABORTED = 6
    REJECTED = 7
    TERMINAL = (SUCCEEDED, CANCELED, ABORTED, REJECTED)

    @classmethod
    def name(cls, value: int) -> str:
        return enum_names(cls).get(value, str(value))


@schema("GoalReply", 1)
class GoalReply(Reply, kw_only=True):
    """Answer to a goal query: `success` is "accepted"; `goal_id` names the goal in feedback,
    result and cancel (empty when rejected, with the reason in `message`)."""

    goal_id: str = ""
    status: int = GoalStatus.UNKNOWN

    @property
    def accepted(self) -> bool:
        return self.success


@schema("CancelRequest", 1)
class CancelRequest(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    goal_id: str


@schema("CancelReply", 1)
class CancelReply(Reply, kw_only=True):
    """`status` is the goal's status after the request (CANCELING or already terminal)."""

    goal_id: str = ""
    status: int = GoalStatus.UNKNOWN


@schema("ResultRequest", 1)
class ResultRequest(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    goal_id: str


def _unwrap(payload: dict[str, Any], type_id: str, cls: type[Message] | None, what: str) -> Any:
    if cls is None:
        if not type_id:
            raise SchemaError(f"{what}: no `{what.lower()}_type` and no type given to unwrap")
        cls = get_schema(type_id)
    try:
        return msgspec.convert(payload, cls)
    except msgspec.ValidationError as e:
        raise SchemaError(f"{what}: {cls.__schema_name__}: {e}") from None


@schema("ActionFeedback", 1)
class ActionFeedback(Message, kw_only=True):
    """Progress of one goal (`<area>/action/<name>/feedback`). `feedback` is the action's
    Feedback message as a plain map; `feedback_type` its schema id (e.g. "TakeoffFeedback@1")."""

    header: Header = msgspec.field(default_factory=Header)
    goal_id: str = ""
    action: str = ""
    status: int = GoalStatus.EXECUTING
    feedback_type: str = ""
    feedback: dict[str, Any] = {}

    @classmethod
    def wrap(cls, goal_id: str, feedback: Message, action: str = "", status: int = GoalStatus.EXECUTING,
             header: Header | None = None) -> "ActionFeedback":
        return cls(header=header or Header(), goal_id=goal_id, action=action, status=status,
                   feedback_type=schema_id(type(feedback)), feedback=to_builtins(feedback))

    def unwrap(self, cls: type[Message] | None = None) -> Any:
        """The typed Feedback (looked up from `feedback_type` unless `cls` is given)."""
        return _unwrap(self.feedback, self.feedback_type, cls, "Feedback")


@schema("ActionResult", 1)
class ActionResult(Reply, kw_only=True):
    """Final outcome of one goal (published on, and queryable at, `<area>/action/<name>/result`).

    `success`/`message` repeat the inner result's so generic clients need not unwrap; a query for
    an unknown goal id gets success=False, status UNKNOWN and an empty `result`.
    """

    goal_id: str = ""
    action: str = ""
    status: int = GoalStatus.UNKNOWN
    result_type: str = ""
    result: dict[str, Any] = {}

    @classmethod
    def wrap(cls, goal_id: str, result: Reply, status: int, action: str = "",
             header: Header | None = None) -> "ActionResult":
        return cls(header=header or Header(), success=result.success, message=result.message,
                   goal_id=goal_id, action=action, status=status,
                   result_type=schema_id(type(result)), result=to_builtins(result))

    def unwrap(self, cls: type[Message] | None = None) -> Any:
        """The typed Result (looked up from `result_type` unless `cls` is given)."""
        return _unwrap(self.result, self.result_type, cls, "Result")


class ActionSpec(NamedTuple):
    goal: type[Message]
    result: type[Reply]
    feedback: type[Message]


# Keyed by the action's key segment: mission/action/{takeoff,land,goto,set_trajectory}.
ACTIONS: dict[str, ActionSpec] = {
    "takeoff": ActionSpec(TakeoffGoal, TakeoffResult, TakeoffFeedback),
    "land": ActionSpec(LandGoal, LandResult, LandFeedback),
    "goto": ActionSpec(GoToPositionGoal, GoToPositionResult, GoToPositionFeedback),
    "set_trajectory": ActionSpec(SetTrajectoryGoal, SetTrajectoryResult, SetTrajectoryFeedback),
}
