"""Process shell: wires MissionManager to Zenoh (inputs, fmu calls, actions, status)."""
from __future__ import annotations

import math
import time

import numpy as np

from aeroperception.schemas import (
    ArmReply, ArmRequest, DiagnosticStatus, Empty, GcsLink, GetMissionReply, GoToPositionGoal,
    GoToPositionResult, LandGoal, LandResult, LoadMissionReply, LoadMissionRequest, MissionCommand, MissionGoal,
    OccupancyGrid, ParamList, PerceptionHealth, Reply, SafetyStatus, SchemaError, SetModeReply,
    SetModeRequest, SetTrajectoryGoal, SetTrajectoryResult, TakeoffGoal, TakeoffResult,
    TrajectoryStatus, Vector3, VehicleState, WaypointReached, load_mission_file, parse_mission,
)
from aeroperception.services.runtime import ActionServer, CallError, GoalHandle, Health, ParamError, Service, run
from aeroperception.services.runtime.state_store import StateStore, default_state_dir

from . import contract
from .actions import MOVING, ActionRun, forward
from .config import MissionConfig
from .fsm import GoalOut, MissionManager, State
from .goals import goal_message
from .limits import obstacle_warning, waypoints_in_obstacles
from .requests import Outcome
from .trajectory import TRAJECTORY_END_RADIUS_M, TrajectoryHandover, check_given
from .uav_status import GcsLinkWatch, UavStatusBuilder, mission_progress_pct

PLANNER_STATUS_FRESH_S = 1.0   # planner/status comes at 10 Hz: older = the planner's parts unknown
PLANNER_PARAMS_PERIOD_S = 3.0  # how often UAVStatus asks the planner for its live hover speed


class ZenohBridge:
    """fmu/srv/* calls without blocking the service: results come back under node.lock."""

    def __init__(self, svc: "MissionService"):
        self.svc = svc

    def _call(self, key, req, reply_cls, answer) -> None:
        def cb(res) -> None:
            if isinstance(res, CallError):
                answer(False, str(res))
            else:
                answer(res.success, res.message)
        self.svc.node.call_async(key, req, reply_cls, cb, timeout_s=self.svc.cfg.bridge_timeout_s)

    def arm(self, arm, answer) -> None:
        self._call("fmu/srv/arm", ArmRequest(arm=arm), ArmReply, answer)

    def set_mode(self, mode, answer) -> None:
        self._call("fmu/srv/set_mode", SetModeRequest(mode=mode), SetModeReply, answer)


class MissionService(Service):
    """Mission manager: 5-state FSM, mission loading, takeoff/land/goto actions."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = MissionConfig      # geofence values that do not make a fence fail at start, are refused live

    def start(self) -> None:
        c, node = self.cfg, self.node
        self.mgr = MissionManager(ZenohBridge(self), self._publish_goal, c.fsm, log=self.log.info, limits=c.limits)
        self.mgr.on_waypoint_reached = self._on_reached
        self.handover = TrajectoryHandover()
        self.costmap: OccupancyGrid | None = None   # the latest, for the load-time obstacle check
        self.planner_status: TrajectoryStatus | None = None
        self.planner_status_rx_s = 0.0
        self.safety: SafetyStatus | None = None
        self.uav = UavStatusBuilder(node.vehicle or "default")
        self.gcs = GcsLinkWatch()
        self.last_goal: MissionGoal | None = None
        self.actions: list[tuple[ActionRun, GoalHandle]] = []
        self._restore()
        node.on_liveliness("fmu", lambda name, alive: self.mgr.on_fmu_alive(alive, time.monotonic()))
        node.on_liveliness("planner", lambda name, alive: self.mgr.on_planner_alive(alive, time.monotonic()))
        # Actions (ARCHITECTURE §3) are still declared here: a contract's ACTIONS names only their keys.
        self.servers = {
            "takeoff": ActionServer(node, "mission/action/takeoff", TakeoffGoal, TakeoffResult,
                                    self._takeoff_goal, self._cancel_to_hold),
            "land": ActionServer(node, "mission/action/land", LandGoal, LandResult,
                                 self._land_goal, self._cancel_to_hold),
            "goto": ActionServer(node, "mission/action/goto", GoToPositionGoal, GoToPositionResult,
                                 self._goto_goal, self._cancel_to_hold),
            "set_trajectory": ActionServer(node, "mission/action/set_trajectory", SetTrajectoryGoal,
                                           SetTrajectoryResult, self._trajectory_goal, self._cancel_to_hold),
        }
        node.every(PLANNER_PARAMS_PERIOD_S, self._ask_planner_params, name="planner-params")
        self.status_loop = node.every(1.0 / c.status_rate_hz, self._tick, name="status")
        node.every(0.1, lambda: self.mgr.tick(time.monotonic()), name="watchdog")  # outage within ~0.1 s

    def _restore(self) -> None:
        """Restart: the persisted mission/progress now, the vehicle's state decides on its first
        sample; else mission_file (a bad one reported in the diagnostics: no mission)."""
        c = self.cfg
        self.store = StateStore(c.state_dir or default_state_dir(self.node.vehicle), contract.STATE_FILE)
        try:
            snapshot = self.store.load()
        except ValueError as e:
            self.log.warn("persisted_mission_ignored", error=str(e))
            snapshot = None
        self.mgr.restore(snapshot, time.monotonic())
        self.log.info("restored", path=str(self.store.path), state=(snapshot or {}).get("state"),
                      mission=bool((snapshot or {}).get("mission_json")))
        self.mgr.on_persist = self._persist
        self.file_error = ""
        if c.mission_file and self.mgr.mission is not None:
            self.log.warn("mission_file_skipped", path=c.mission_file, reason=f"restored mission "
                          f"{self.mgr.mission.mission_id or '(unnamed)'} in progress")
        elif c.mission_file:
            self.file_error = self._load_file(c.mission_file)
            if self.file_error:
                self.mgr.message = self.file_error

    def _load_file(self, path: str) -> str:
        """Load mission_file `path` (at start-up unless a restart restored a mission in progress:
        that one is the vehicle's; and when set live): "" when loaded, else why (logged)."""
        try:
            ok, message = self.mgr.load(load_mission_file(path))
        except SchemaError as e:
            ok, message = False, str(e)
        if ok:
            self.log.info("mission_file_loaded", path=path, message=message)
            return ""
        self.log.error("mission_file_refused", path=path, error=message)
        return f"mission_file {path}: {message}"

    def on_config(self, cfg: MissionConfig) -> None:
        """A live set that cannot be honoured is refused (ParamError: the old value stays): a mission
        file that does not load (geofence values that do not make a fence are refused building cfg)."""
        if cfg.mission_file != self.cfg.mission_file and cfg.mission_file:
            why = self._load_file(cfg.mission_file)
            if why:
                raise ParamError(why)
            self.file_error = ""
        if cfg.status_rate_hz != self.cfg.status_rate_hz:
            self.status_loop.set_rate(cfg.status_rate_hz)
        self.mgr.cfg, self.mgr.limits = cfg.fsm, cfg.limits

    def _persist(self, snapshot: dict) -> None:
        try:
            self.store.save(snapshot)
        except OSError as e:
            self.log.throttled("error", "persist", "persist_failed", path=str(self.store.path), error=str(e))

    # ------------------------------------------------------------ inputs (contract.INPUTS)

    def on_state_vehicle(self, m: VehicleState) -> None:
        self.uav.heard_vehicle((self.node.now_ns() - m.header.stamp_ns) * 1e-9)
        self.mgr.on_vehicle(m, time.monotonic())

    def on_perception_health(self, m: PerceptionHealth) -> None:
        self.mgr.on_perception(m.overall_healthy, time.monotonic())

    def on_perception_costmap(self, m: OccupancyGrid) -> None:
        self.costmap = m

    def on_safety_status(self, msg: SafetyStatus) -> None:
        self.safety = msg
        reason = "; ".join(msg.active_errors or msg.active_warnings)
        self.mgr.on_safety(msg.recommended_action, reason)

    def on_planner_status(self, m: TrajectoryStatus) -> None:
        self.planner_status, self.planner_status_rx_s = m, time.monotonic()
        self.mgr.on_planner(m.obstacle_state, m.message, time.monotonic())
        if self.handover.refused(m):
            self.mgr.on_trajectory_refused(m.message)

    def on_gcs_link(self, m: GcsLink) -> None:
        changed = self.gcs.heard(m.connected)
        if changed is not None:
            self.mgr.on_link(changed)

    def on_mission_command(self, msg: MissionCommand) -> Reply:
        if msg.command == MissionCommand.LOAD:
            r = self.on_mission_load(LoadMissionRequest(mission_json=msg.mission_json))
            return Reply(success=r.success, message=r.message)
        ok, message = self.mgr.command(msg.command, waypoint_index=msg.waypoint_index)
        self.log.info("command", command=msg.command, accepted=ok, message=message)
        return Reply(success=ok, message=message)

    # ------------------------------------------------------------ queryables (contract.SERVICES)

    def on_command_request(self, msg: MissionCommand) -> Reply:
        """mission/srv/command: like mission/command, but the reply is the outcome. Commands that
        need the flight controller (ARM, DISARM, TAKEOFF's arming) are answered when fmu has
        answered, so a refused arm is a refused TAKEOFF, not "taking off"."""
        if msg.command == MissionCommand.LOAD:
            with self.node.lock:
                return self.on_mission_command(msg)
        outcome = Outcome()
        with self.node.lock:
            ok, message = self.mgr.command(msg.command, outcome, msg.waypoint_index)
            self.log.info("command", command=msg.command, accepted=ok, message=message)
        if ok and outcome.wait(self.cfg.bridge_timeout_s + 1.0):
            ok, message = outcome.result
        return Reply(success=ok, message=message)

    def on_mission_load(self, req: LoadMissionRequest) -> LoadMissionReply:
        try:
            mission = parse_mission(req.mission_json)
        except SchemaError as e:
            self.log.warn("mission_rejected", error=str(e))
            return LoadMissionReply(success=False, message=f"invalid mission: {e}")
        ok, message = self.mgr.load(mission)
        if ok:
            self.file_error = ""
            inside = waypoints_in_obstacles(mission, self.costmap)
            if inside:
                message += obstacle_warning(inside)
                self.log.warn("waypoints_in_obstacles", waypoints=inside)
        return LoadMissionReply(success=ok, message=message, num_waypoints=len(mission.waypoints) if ok else 0)

    def on_mission_get(self, _req: Empty) -> GetMissionReply:
        m = self.mgr.mission
        if m is None:
            return GetMissionReply(success=False, message="no mission loaded")
        return GetMissionReply(success=True, mission_id=m.mission_id, num_waypoints=len(m.waypoints),
                               mission_json=m.to_json())

    # ------------------------------------------------------------ outputs

    def _publish_goal(self, goal: GoalOut) -> None:
        v = self.mgr.vehicle
        self.last_goal = goal_message(goal, v.yaw_rad if v else None, self.node.header())
        self.io["mission/active_goal"].publish(self.last_goal)
        self._publish_trajectory()

    def _publish_trajectory(self) -> None:
        """The waypoints ahead for the planner's generator (none while not flying them): with
        each goal, and re-sent with the status for late joiners (the planner skips repeats)."""
        mgr = self.mgr
        executing = mgr.state == State.EXECUTING
        goto_m = mgr.goto_target.position_m if executing and mgr.goto_target is not None else None
        self.io["mission/active_trajectory"].publish(
            self.handover.message(executing and goto_m is None, mgr.mission, mgr.wp_index, goto_m))

    def _on_reached(self, index: int, pos: np.ndarray) -> None:
        self.io["mission/waypoint_reached"].publish(WaypointReached(
            header=self.node.header("map"), index=index, mission_id=self.mgr.mission.mission_id,
            position_m=Vector3.from_array(pos)))

    def _tick(self) -> None:
        now = time.monotonic()
        self.mgr.tick(now)
        st = self.mgr.status()
        st.header = self.node.header()
        self.io["mission/status"].publish(st)
        self._publish_uav_status()
        if self.last_goal is not None:  # latch for late joiners (planner restart)
            self.io["mission/active_goal"].publish(self.last_goal)
            self._publish_trajectory()
        forward(self.actions, self.mgr)

    def _ask_planner_params(self) -> None:
        """UAVMode's hover speed is the planner's live one (a planner not answering: the last heard)."""
        def answer(res) -> None:
            if isinstance(res, ParamList):
                self.uav.heard_planner_params({d.name: d.value for d in res.params})
        self.node.call_async("config/planner/@params", None, ParamList, answer, timeout_s=1.0)

    def _publish_uav_status(self) -> None:
        fresh = time.monotonic() - self.planner_status_rx_s < PLANNER_STATUS_FRESH_S
        m = self.mgr.mission
        msg = self.uav.build(self.mgr.state, self.mgr.vehicle, self.safety, self.planner_status if fresh else None,
                             bool(self.gcs.up), m.mission_id if m is not None else "",
                             mission_progress_pct(self.mgr.state, m, self.mgr.wp_index))
        msg.header = self.node.header()
        self.io["mission/uav_status"].publish(msg)

    # ------------------------------------------------------------ actions

    def _takeoff_goal(self, h: GoalHandle) -> str | None:
        outcome = Outcome()
        ok, message = self.mgr.takeoff(h.goal.target_altitude_m, outcome, h.goal.climb_rate_mps)
        return self._accepted(h, ActionRun("takeoff", h.goal, outcome), ok, message)

    def _land_goal(self, h: GoalHandle) -> str | None:
        g: LandGoal = h.goal
        target = None if g.land_at_current_position else g.target_position_m.to_array()
        ok, message = self.mgr.land(target, g.descent_rate_mps)
        return self._accepted(h, ActionRun("land", g), ok, message)

    def _goto_goal(self, h: GoalHandle) -> str | None:
        g: GoToPositionGoal = h.goal
        yaw = g.yaw_rad if g.yaw_rad is not None and math.isfinite(g.yaw_rad) else None
        ok, message = self.mgr.goto(g.position_m.to_array(), yaw, g.acceptance_radius_m, g.velocity_mps)
        return self._accepted(h, ActionRun("goto", g), ok, message)

    def _trajectory_goal(self, h: GoalHandle) -> str | None:
        """Fly a given trajectory: checked here as the planner will make it (from where the vehicle
        is), then a goto to its end with the trajectory handed to the planner on the way."""
        g: SetTrajectoryGoal = h.goal
        v = self.mgr.vehicle
        if v is None:
            return "no vehicle state yet"
        why, end = check_given(g, v.position_m.to_array(), v.yaw_rad, self.mgr.acceptance_radius_m())
        if why:
            return why
        ok, message = self.mgr.goto(end, None, TRAJECTORY_END_RADIUS_M)
        if ok:
            self.handover.give(g.trajectory, end)
            self._publish_trajectory()
        return self._accepted(h, ActionRun("trajectory", g, status=lambda: self.planner_status), ok, message)

    def _accepted(self, h: GoalHandle, run: ActionRun, ok: bool, message: str) -> str | None:
        """None (accepted: `run` is stepped from now on) or why the goal is refused."""
        if not ok:
            return message
        self.actions.append((run, h))
        return None

    def _cancel_to_hold(self, h: GoalHandle) -> bool:
        return self.mgr.state in MOVING

    def health(self) -> Health:
        v = self.mgr.vehicle
        level = DiagnosticStatus.OK if v is not None and v.connected else DiagnosticStatus.WARN
        if self.mgr.outage or self.file_error:
            level = DiagnosticStatus.WARN
        return Health(level, f"{self.mgr.state.value}: {self.file_error or self.mgr.message}",
                      {"state": self.mgr.state.value, "waypoint": self.mgr.wp_index,
                       "perception_healthy": self.mgr.perception_healthy,
                       "vehicle": "connected" if v is not None and v.connected else "no state",
                       "fc_mode": v.flight_mode if v is not None else "", "outage": self.mgr.outage or "none",
                       "safety_action": self.mgr.safety_action, "state_file": str(self.store.path)})


def main(argv=None) -> int:
    return run(MissionService, argv)
