"""What gcs asks of the stack: every call into it that a MAVLink request leads to, each answering
one `Outcome`.

An operation takes one argument, `done(outcome)`, and calls it once, later (node.call_async's
reply, under the service's lock). An operation made of several calls says how they chain:
`in_order` (each only once the one before succeeded: take off, then start the mission) or
`first_of` (the next only when the one before was refused: HOLD through the mission manager,
else through the flight controller).

Mission-scoped speed (mission_speed.py) lives here too, because starting a mission, a
DO_CHANGE_SPEED command and the mission's own progress all move the planner's speed limit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

from aeroperception.schemas import (
    ArmReply, ArmRequest, Empty, GetMissionReply, GoalReply, GoToPositionGoal, LoadMissionReply, LoadMissionRequest,
    MissionCommand, MissionStatus, ParamList, ParamSet, ParamSetReply, Reply, SetModeReply, SetModeRequest,
    TakeoffGoal, Vector3,
)
from aeroperception.services.runtime import CallError

from .mission_progress import Progress
from .mission_speed import SPEED_DEFAULT, SpeedSchedule
from .params import ParamTable
from .telemetry import TelemetryState

SPEED_SERVICE, SPEED_PARAM = "planner", "max_velocity_mps"   # DO_CHANGE_SPEED sets this
PARAMS_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class Outcome:
    """The stack's final answer to one operation: done (ok), refused (-> DENIED), or no answer
    at all (`failed`: the call timed out or nobody serves it -> FAILED)."""

    ok: bool
    message: str = ""
    failed: bool = False

    @classmethod
    def of(cls, reply: Any) -> "Outcome":
        """A service's reply (success, message), or the CallError of a call that got none."""
        if isinstance(reply, CallError):
            return cls(False, str(reply), failed=True)
        return cls(bool(reply.success), reply.message)


Done = Callable[[Outcome], None]
Operation = Callable[[Done], None]
Call = Callable[..., None]   # node.call_async(key, request, reply_type, on_reply, timeout_s=...)


def in_order(steps: Sequence[Operation], done: Done) -> None:
    """Run the steps one after another while they succeed; `done` gets the first refusal or
    failure, else the last outcome."""
    _chain(list(steps), done, stop_when_ok=False)


def first_of(steps: Sequence[Operation], done: Done) -> None:
    """Try the steps one after another until one succeeds; `done` gets that outcome, else the
    last one's."""
    _chain(list(steps), done, stop_when_ok=True)


def _chain(steps: list[Operation], done: Done, stop_when_ok: bool) -> None:
    def run(i: int) -> None:
        def after(outcome: Outcome) -> None:
            if outcome.ok == stop_when_ok or i + 1 == len(steps):
                done(outcome)
            else:
                run(i + 1)
        steps[i](after)
    run(0)


class StackOps:
    """The operations object: what commands, modes, missions and parameters from ground stations
    become in the stack (the `Ops` commands.CommandHandler uses, and more).

    call: node.call_async; timeout_s: how long each call may take. tel.mission is the last
    mission/status, progress.wp_seqs the loaded mission's waypoints, table the parameters.
    """

    def __init__(self, call: Call, timeout_s: float, table: ParamTable, tel: TelemetryState, progress: Progress,
                 log: Any):
        self.call = call
        self.timeout_s = timeout_s
        self.table = table
        self.tel = tel
        self.progress = progress
        self.log = log
        self.speeds = SpeedSchedule()    # the loaded mission's DO_CHANGE_SPEED items, per waypoint

    def _ask(self, key: str, request: Any, reply_type: type, done: Done) -> None:
        self.call(key, request, reply_type, lambda reply: done(Outcome.of(reply)), timeout_s=self.timeout_s)

    # ------------------------------------------------------------ vehicle and mission

    def arm(self, arm: bool, force: bool, done: Done) -> None:
        self._ask("fmu/srv/arm", ArmRequest(arm=arm, force=force), ArmReply, done)

    def mission_command(self, command: str, done: Done) -> None:
        self._ask("mission/srv/command", MissionCommand(command=command), Reply, done)

    def jump_to(self, waypoint: int, done: Done) -> None:
        """The mission flies to `waypoint` (0-based) next."""
        self._ask("mission/srv/command", MissionCommand(command="SET_CURRENT", waypoint_index=waypoint), Reply, done)

    def _fmu_set_mode(self, mode: str, done: Done) -> None:
        self._ask("fmu/srv/set_mode", SetModeRequest(mode=mode), SetModeReply, done)

    def set_mode(self, mode: str, done: Done) -> None:
        if mode == "MISSION":
            self.mission_start(done)
        elif mode == "TAKEOFF":
            self.takeoff(None, done)
        elif mode in ("HOLD", "LAND", "RTL"):
            # Through the mission manager (so it stops pushing goals); on the ground it refuses,
            # then the flight controller decides.
            first_of([lambda d: self.mission_command(mode, d), lambda d: self._fmu_set_mode(mode, d)], done)
        else:
            self._fmu_set_mode(mode, done)

    def mission_start(self, done: Done) -> None:
        st = self.tel.mission
        # The mission manager (re)starts at its active waypoint, or at 0 when not started/complete.
        self.speeds.reset()
        k = st.active_waypoint if st is not None and 0 <= st.active_waypoint < len(self.progress.wp_seqs) else 0
        self.apply_mission_speed(k)
        # On the ground: take off first; the mission manager starts the mission once up.
        commands = ("TAKEOFF", "START") if st is not None and st.state == MissionStatus.STATE_IDLE else ("START",)

        def started(outcome: Outcome) -> None:
            if not outcome.ok:
                self.end_speed_scope("mission start failed")
            done(outcome)

        in_order([lambda d, c=c: self.mission_command(c, d) for c in commands], started)

    def takeoff(self, altitude_m: float | None, done: Done) -> None:
        if altitude_m is None:
            self.mission_command("TAKEOFF", done)
            return
        self._ask("mission/action/takeoff/goal", TakeoffGoal(target_altitude_m=altitude_m), GoalReply, done)

    def goto(self, enu: tuple[float, float, float], yaw_rad: float | None, done: Done) -> None:
        goal = GoToPositionGoal(position_m=Vector3(x=enu[0], y=enu[1], z=enu[2]), yaw_rad=yaw_rad)
        self._ask("mission/action/goto/goal", goal, GoalReply, done)

    def load_mission(self, mission_json: str, on_reply: Callable[[Any], None]) -> None:
        self.call("mission/srv/load", LoadMissionRequest(mission_json=mission_json), LoadMissionReply, on_reply,
                  timeout_s=self.timeout_s)

    def get_mission(self, on_reply: Callable[[Any], None]) -> None:
        self.call("mission/srv/get", Empty(), GetMissionReply, on_reply, timeout_s=self.timeout_s)

    # ------------------------------------------------------------ parameters

    def list_params(self, service: str, on_reply: Callable[[Any], None]) -> None:
        self.call(f"config/{service}/@params", None, ParamList, on_reply, timeout_s=PARAMS_TIMEOUT_S)

    def set_param(self, service: str, name: str, value: Any, on_reply: Callable[[ParamSetReply], None]) -> None:
        """A service's parameter; on_reply gets its ParamSetReply (a failed call as a refusal)."""
        def reply(res: Any) -> None:
            on_reply(ParamSetReply(success=False, message=str(res)) if isinstance(res, CallError) else res)
        self.call(f"config/{service}/@set", ParamSet(name=name, value=value), ParamSetReply, reply,
                  timeout_s=self.timeout_s)

    # ------------------------------------------------------------ the planner's speed

    def change_speed(self, speed_mps: float | None, done: Done) -> None:
        """DO_CHANGE_SPEED (command): the planner's live speed limit; None = its declared default.
        While our mission runs the change is mission-scoped (ends with it, mission_speed.py)."""
        st = self.tel.mission
        if st is not None and st.mission_id == self.speeds.mission_id and st.state in SpeedSchedule.RUNNING:
            self.speeds.begin(self._planner_speed())
        self._set_planner_speed(speed_mps, done)

    def _planner_speed(self) -> float | None:
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        return float(found[1].value) if found is not None else None

    def _set_planner_speed(self, speed_mps: float | None, done: Done) -> None:
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        if speed_mps is None:
            if found is None or found[1].default is None:
                done(Outcome(False, f"{SPEED_SERVICE}.{SPEED_PARAM} default unknown (is the planner running?)"))
                return
            speed_mps = float(found[1].default)

        def reply(res: Any) -> None:
            if not isinstance(res, CallError) and res.success and res.value is not None:
                self.table.set_value(SPEED_SERVICE, SPEED_PARAM, res.value)
            if not isinstance(res, CallError) and not res.success:
                self.log.warn("change_speed_rejected", speed_mps=speed_mps, error=res.message)
            done(Outcome.of(res))

        self.call(f"config/{SPEED_SERVICE}/@set", ParamSet(name=SPEED_PARAM, value=float(speed_mps)), ParamSetReply,
                  reply, timeout_s=self.timeout_s)

    def new_mission_speeds(self, speeds: list[float | None], mission_id: str) -> None:
        """Another mission is loaded: the previous one's speed scope ends, its items' speeds rule."""
        self.end_speed_scope("mission replaced")
        self.speeds = SpeedSchedule(speeds, mission_id)

    def apply_mission_speed(self, k: int) -> None:
        """The vehicle flies to waypoint k of our mission: the speed its items ask for there."""
        speed = self.speeds.due(k)
        if speed is None:
            return
        self.speeds.begin(self._planner_speed())
        self.log.info("mission_speed", waypoint=k, speed_mps=speed if speed != SPEED_DEFAULT else "default")
        self._set_planner_speed(None if speed == SPEED_DEFAULT else speed,
                                lambda o: None if o.ok else self.log.warn("mission_speed_failed", error=o.message))

    def observe_mission(self, msg: MissionStatus) -> None:
        """mission/status: our mission's speed where it runs, the speed from before once it is over."""
        if msg.state == MissionStatus.STATE_EXECUTING and msg.mission_id == self.speeds.mission_id:
            self.apply_mission_speed(msg.active_waypoint)   # however the mission was started
        restore = self.speeds.observe(msg.mission_id, msg.state, msg.active_waypoint, msg.total_waypoints)
        if restore is not None:
            self._restore_speed(restore, f"mission {self.speeds.mission_id or '-'} over ({msg.state})")

    def end_speed_scope(self, why: str) -> None:
        restore = self.speeds.end()
        if restore is not None:
            self._restore_speed(restore, why)

    def _restore_speed(self, speed_mps: float, why: str) -> None:
        """The mission that changed the planner's speed is over: the speed from before it."""
        self.log.info("mission_speed_restored", speed_mps=speed_mps, reason=why)
        self._set_planner_speed(speed_mps, lambda o: None if o.ok else self.log.warn(
            "mission_speed_restore_failed", speed_mps=speed_mps, error=o.message))
