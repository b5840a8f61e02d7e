"""Process shell: state + goal from Zenoh, 50 Hz setpoints out."""
from __future__ import annotations

import time

import numpy as np

from aeroperception.schemas import (
    DiagnosticStatus, Header, LandedState, MissionGoal, OccupancyGrid, Odometry, SelectPluginReply, SelectPluginRequest, Trajectory,
    TrajectorySetpoint, TrajectoryStatus, Vector3, VehicleState, WaypointReached,
)
from aeroperception.services.runtime.state_store import StateStore, default_state_dir
from aeroperception.services.runtime import Health, LatestWorker, ParamError, Service, run

from . import contract
from .avoidance import LocalPlanner
from .config import PlannerConfig
from .controllers import CONTROLLERS, Gains
from .estimators import VioEstimate, fc_offset_m
from .logic import Goal, GoalWatchdog, WaypointPlanner, tracking_errors
from .plugins import PARTS_FILE, REGISTRIES, restore_parts, selected_parts, switch_refusal
from .state_delay import StateDelay
from .tracking import TrajectoryTracker, start_velocity_mps


class PlannerService(Service):
    """50 Hz waypoint planner (requirement PLAN-1)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = PlannerConfig

    def start(self) -> None:
        self._restore_parts()    # before on_config: a restart keeps what flew
        p = self.cfg
        self.planner = WaypointPlanner(p.max_velocity_mps, p.kp, p.acceptance_radius_m)
        self.state: VehicleState | None = None        # the active estimator's, in the map frame
        self.fc_state: VehicleState | None = None     # the flight controller's (state/vehicle)
        self.vio = VioEstimate()
        self.odom_rx_s: float | None = None
        self.state_delay = StateDelay()     # a backlog after a stall is dropped (state_delay.py)
        self.state_rx_s = 0.0
        self.last_distance: float | None = None
        self.last_setpoint: TrajectorySetpoint | None = None   # what fmu was last sent
        self.goal_msg: MissionGoal | None = None
        self.goals_received = 0
        self.goal_watch = GoalWatchdog(p.goal_timeout_s)
        self.pub_sp = self.io["fmu/in/trajectory_setpoint"]
        self.pub_status = self.io["planner/status"]
        self.pub_reached = self.io["planner/waypoint_reached"]
        # Obstacles: plans run on their own thread (10-30 ms), the setpoint path only steers.
        self.avoid = LocalPlanner(p.avoidance)
        self.obstacle_state, self.obstacle_reason = ("off", "") if not p.obstacle_avoidance else ("no_costmap", "")
        self.replanner = LatestWorker(lambda pg: self.avoid.replan(*pg), "planner-replan",
                                      on_error=lambda e: self.log.throttled("error", "replan", "replan_failed",
                                                                            error=f"{type(e).__name__}: {e}"))
        # Trajectories: the mission's whole way, flown while its goal is on it (tracking.py).
        self.tracker = TrajectoryTracker(p.tracker)
        self.trajectory_msg: Trajectory | None = None
        self.tracking_error_m: float | None = None     # vehicle to the trajectory's reference, while flying one
        self.last_pub_s = 0.0
        self.loop = self.node.every(1.0 / p.rate_hz, self._tick, name="setpoint")
        self.node.every(1.0 / contract.STATUS_RATE_HZ, self._publish_status, name="status")

    def stop(self) -> None:
        self.replanner.stop()

    def on_perception_costmap(self, msg: OccupancyGrid) -> None:
        o = msg.origin.position
        self.avoid.set_costmap(msg.data.to_numpy(), (o.x, o.y), msg.resolution_m, time.monotonic())
        self._maybe_replan()

    def _maybe_replan(self) -> None:
        g = self.planner.goal
        if g is None or not self.state_fresh() or not self.cfg.obstacle_avoidance:
            return
        pos = self.state.position_m.to_array()
        if self.avoid.needs_plan(pos, g.position_m):
            self.replanner.offer((pos, g.position_m.copy()))

    def on_mission_active_trajectory(self, msg: Trajectory) -> None:
        if msg == self.trajectory_msg:
            return  # re-sent at 2 Hz for late joiners: already taken
        self.trajectory_msg = msg
        self.tracker.offer(msg, time.monotonic())
        self.log.info("trajectory", trajectory_id=msg.trajectory_id, generator=msg.generator_name,
                      type=msg.trajectory_type, waypoints=len(msg.waypoints))

    def _path_blocked(self, points_xy) -> bool:
        return self.avoid.path_blocked(points_xy, time.monotonic())

    def on_planner_select_plugin(self, req: SelectPluginRequest) -> SelectPluginReply:
        """SetTrajectoryGenerator / SetController / SetEstimator: the slot's parameter, set live
        (plugins.py's rule refuses it moving; the parameter's choices list what exists)."""
        r = self.node.set_param(req.role, req.name)
        return SelectPluginReply(success=r.success, message=r.message, active=self.params[req.role])

    def _vio_fresh(self) -> bool:
        return self.odom_rx_s is not None and time.monotonic() - self.odom_rx_s < self.cfg.state_timeout_s

    def _restore_parts(self) -> None:
        self.parts_store = StateStore(self.cfg.state_dir or default_state_dir(self.node.vehicle), PARTS_FILE)
        self.parts_restored: list[str] = []
        try:
            saved = self.parts_store.load()
        except ValueError as e:
            self.log.warn("persisted_parts_ignored", error=str(e))
            return
        self.parts_restored = restore_parts(saved, self.params)
        for note in self.parts_restored:
            self.log.warn("parts_restored", note=note)

    def _save_parts(self) -> None:
        try:
            self.parts_store.save(selected_parts(self.params))
        except OSError as e:
            self.log.throttled("error", "parts", "parts_persist_failed", path=str(self.parts_store.path), error=str(e))

    def _switch(self, role: str, name: str) -> None:
        """A part switched (the rule already passed): what changes with it."""
        if role == "trajectory_generator":
            self.tracker.set_generator(name)
        elif role == "estimator":
            self.vio.alignment = None          # aligned anew, now, with the flight controller's estimate
            self.state_delay.reset()           # another source's stamps
        self.log.info("plugin_switched", role=role, name=name)

    def on_config(self, cfg: PlannerConfig) -> None:
        """A parameter changed (one at a time: a live set): a part switched only by plugins.py's rule."""
        old = self.cfg
        switched = [role for role in REGISTRIES if getattr(cfg, role) != getattr(old, role)]
        for role in switched:
            why = switch_refusal(role, getattr(cfg, role), self.state or self.fc_state, old.hover_speed_mps,
                                 self._vio_fresh())
            if why:
                raise ParamError(f"{role} stays {getattr(old, role)!r}: {why}")
        self.tracker.cfg = cfg.tracker       # the next trajectory made uses it
        self.avoid.cfg = cfg.avoidance
        for role in switched:
            self._switch(role, getattr(cfg, role))
            self._save_parts()
        if cfg.obstacle_avoidance != old.obstacle_avoidance:
            self.obstacle_state, self.obstacle_reason = ("no_costmap", "") if cfg.obstacle_avoidance else ("off", "")
        self.goal_watch.timeout_s = cfg.goal_timeout_s
        self.planner.max_velocity_mps, self.planner.kp = cfg.max_velocity_mps, cfg.kp
        self.planner.acceptance_radius_m = cfg.acceptance_radius_m
        if cfg.rate_hz != old.rate_hz:
            self.loop.set_rate(cfg.rate_hz)

    def on_state_vehicle(self, msg: VehicleState) -> None:
        self.fc_state = msg
        if self.cfg.estimator == "fc":
            self._take_state(msg)

    def on_state_visual_odometry(self, msg: Odometry) -> None:
        self.odom_rx_s = time.monotonic()
        if self.cfg.estimator == "vio":
            est = self.vio.estimate(msg, self.fc_state)
            if est is not None:
                self._take_state(est)

    def _take_state(self, msg: VehicleState) -> None:
        """The active estimator's state (estimators.py), in the map frame."""
        if self.state_delay.stale(self.node.now_ns(), msg.header.stamp_ns, self.cfg.state_timeout_s):
            return   # a backlog delivered after this process stalled: never planned from
        if not self.state_fresh():
            # Back after a gap (fmu restart, FC link, router restart): the vehicle moved without us
            # and the mission re-checks it after an outage. Hold where it is until the mission's goal
            # comes again (it re-sends it at 2 Hz), never on to a goal from before the gap.
            self._forget_goal()
        elif msg.flight_mode not in ("", "OFFBOARD") and msg.landed_state != LandedState.ON_GROUND:
            # The FC flies a mode of its own: our hold follows the vehicle (landed, there is nothing to
            # hold, and PX4's estimate may wander: after a GPS loss it drifted 2 m into the ground)
            self.planner.retake_hold()
        self.state, self.state_rx_s = msg, time.monotonic()
        self._cycle()  # event-driven: a fresh state goes out as a setpoint at once (hot path)

    def _tick(self) -> None:
        """The 50 Hz deadline loop: guarantees the rate when state arrives slower or late."""
        if time.monotonic() - self.last_pub_s > 1.25 * self.loop.period_s:
            self._cycle()

    def on_mission_active_goal(self, msg: MissionGoal) -> None:
        if self.goal_watch.heard(time.monotonic()):
            self.log.info("mission_back", note="goal stream resumed: following the mission's goal")
        if msg == self.goal_msg:
            return  # mission re-publishes its latest goal at 2 Hz for late joiners: already applied
        self.goal_msg = msg
        if msg.header.frame_id == MissionGoal.HOLD_FRAME:
            self.planner.set_goal(None)
            return
        yaw = msg.pose.orientation.to_yaw()
        self.goals_received += 1
        self.planner.set_goal(Goal(msg.pose.position.to_array(), yaw, self.goals_received,
                                   msg.max_speed_mps, msg.max_vertical_speed_mps))

    def _mission_goal_m(self):
        g = self.goal_msg
        return None if g is None or g.header.frame_id == MissionGoal.HOLD_FRAME else g.pose.position.to_array()

    def state_fresh(self) -> bool:
        return self.state is not None and time.monotonic() - self.state_rx_s < self.cfg.state_timeout_s

    def _cycle(self) -> None:
        if not self.state_fresh():
            return  # no state: send nothing; fmu holds on its own after 100 ms of silence
        st = self.state
        if self.planner.goal is not None and self.tracker.holds_for(self._mission_goal_m()):
            self.planner.set_goal(None)     # a refused given trajectory is not flown goal by goal (status says why)
        res = self.planner.step(st.position_m.to_array(), st.yaw_rad, time.monotonic())
        follow = None
        if self.planner.goal is not None:
            age_s = self.state_delay.age_s(self.node.now_ns(), st.header.stamp_ns, self.cfg.state_timeout_s)
            follow = self.tracker.step(st.position_m.to_array(), st.yaw_rad, time.monotonic(), self.planner.goal.position_m,
                                       self._path_blocked if self.cfg.obstacle_avoidance else None, age_s,
                                       self._start_velocity_mps(st))
        self.tracking_error_m = follow.tracking_error_m if follow is not None else None
        if follow is not None:
            res.setpoint = follow.setpoint       # the trajectory is clear of obstacles ahead (checked in step)
            if self.cfg.obstacle_avoidance:
                self.obstacle_state, self.obstacle_reason = "clear", ""
        elif self.cfg.obstacle_avoidance and self.planner.goal is not None:
            out = self.avoid.adjust(st.position_m.to_array(), self.planner.goal.position_m,
                                    res.setpoint.velocity_mps.to_array(), time.monotonic())
            res.setpoint.velocity_mps = Vector3.from_array(out.velocity_mps)
            self.obstacle_state, self.obstacle_reason = out.state, out.reason
        elif self.cfg.obstacle_avoidance:
            self.obstacle_state, self.obstacle_reason = "clear", ""   # holding: no verdict about an old goal
        res.setpoint = self._to_fc(res.setpoint, st)
        res.setpoint.header = Header(stamp_ns=st.header.stamp_ns, frame_id="map")
        self.pub_sp.publish(res.setpoint)
        self.last_setpoint = res.setpoint
        self.last_pub_s = time.monotonic()
        self.last_distance = res.distance_m
        if res.reached and self.planner.goal is not None:
            g = self.planner.goal
            self.pub_reached.publish(WaypointReached(header=self.node.header("map"), index=g.index,
                                                     position_m=st.position_m))
            self.log.info("waypoint_reached", index=g.index, distance_m=round(res.distance_m, 3))

    def _start_velocity_mps(self, st: VehicleState) -> np.ndarray:
        sp = self.last_setpoint
        return start_velocity_mps(sp.velocity_mps.to_array() if sp is not None and sp.velocity_valid else None,
                                  time.monotonic() - self.last_pub_s, self.loop.period_s, st.velocity_mps.to_array())

    def _to_fc(self, sp: TrajectorySetpoint, st: VehicleState) -> TrajectorySetpoint:
        """The reference as the active controller gives it to the flight controller, its position
        in the flight controller's own estimate (estimators.fc_offset_m)."""
        p = self.cfg
        sp = CONTROLLERS[p.controller].apply(sp, st.position_m.to_array(), Gains(p.kp, p.max_velocity_mps))
        if sp.position_valid:
            sp.position_m = Vector3.from_array(sp.position_m.to_array() + fc_offset_m(self.fc_state, st))
        return sp

    def _check_goal_stream(self) -> None:
        if self.goal_watch.expired(time.monotonic(), self.planner.goal is not None):
            self._forget_goal()
            self.log.warn("mission_silent", timeout_s=self.cfg.goal_timeout_s,
                          note="no goal from the mission (mission or ground link down): holding")

    def _forget_goal(self) -> None:
        """Hold here; forget the goal so the mission's next message (re-sent or new) applies."""
        self.planner.set_goal(None)
        self.goal_msg = None

    def _publish_status(self) -> None:
        self._check_goal_stream()
        fresh = self.state_fresh()
        status = self.planner.status if fresh else TrajectoryStatus.STATUS_ERROR
        p = self.cfg
        msg = TrajectoryStatus(header=self.node.header("map"), status=status, trajectory_id=f"goal-{self.goals_received}",
                               obstacle_state=self.obstacle_state, message=self.obstacle_reason,
                               active_trajectory_generator=p.trajectory_generator, active_controller=p.controller,
                               active_estimator=p.estimator)
        why = self.tracker.refused or self.tracker.blocked
        if why and not msg.message:
            msg.message = why
        if fresh and self.last_setpoint is not None:
            position = self.state.position_m.to_array()
            p = self.planner.progress(position, time.monotonic())
            msg.progress_percent, msg.elapsed_time_s, msg.remaining_time_s = p.percent, p.elapsed_s, p.remaining_s
            msg.current_setpoint = self.last_setpoint
            msg.position_error_m, msg.velocity_error_mps = tracking_errors(self.last_setpoint, self.planner, position,
                                                                           self.state.velocity_mps.to_array())
            along = self.tracker.progress(time.monotonic()) if self.tracking_error_m is not None else None
            if along is not None:    # flying the trajectory: progress along it, error against its reference
                msg.trajectory_id = self.tracker.trajectory_id
                msg.progress_percent, msg.elapsed_time_s, msg.remaining_time_s = along
                msg.position_error_m = self.tracking_error_m
        if self.tracker.holds_for(self._mission_goal_m()):
            msg.trajectory_id, msg.status = self.tracker.trajectory_id, TrajectoryStatus.STATUS_ABORTED
            msg.message = f"trajectory refused: {self.tracker.refused}"
        self.pub_status.publish(msg)
        self._maybe_replan()   # 10 Hz: the vehicle moved on since the last costmap

    def health(self) -> Health:
        if not self.state_fresh():
            return Health(DiagnosticStatus.ERROR, "no fresh state/vehicle: not publishing setpoints")
        values = {"distance_m": self.last_distance if self.last_distance is not None else "n/a",
                  "trajectory": self.tracker.trajectory_id if self.tracking_error_m is not None else "-",
                  "trajectory_generator": self.cfg.trajectory_generator, "controller": self.cfg.controller,
                  "estimator": self.cfg.estimator, "flying_with": self.tracker.generator() or "-",
                  "parts_restored": "; ".join(self.parts_restored) or "-",
                  "trajectories_made": self.tracker.built, "trajectories_resumed": self.tracker.resumed,
                  "waypoints_counted_late": self.tracker.late_counts,
                  "obstacles": self.obstacle_state, "replans": self.replanner.processed,
                  "stale_states_dropped": self.state_delay.stale_count}
        if self.obstacle_state in ("blocked", "unreachable", "stale_costmap"):
            return Health(DiagnosticStatus.WARN, f"holding: {self.obstacle_reason}", values)
        if self.tracker.holds_for(self._mission_goal_m()):
            return Health(DiagnosticStatus.WARN, f"holding: trajectory refused: {self.tracker.refused}", values)
        if self.tracker.refused:
            return Health(DiagnosticStatus.WARN, f"trajectory refused, flying goal by goal: {self.tracker.refused}", values)
        if self.goal_watch.silent:
            return Health(DiagnosticStatus.WARN, "holding: no goal from the mission for "
                          f"{self.cfg.goal_timeout_s:g} s (mission or ground link down)", values)
        return Health(DiagnosticStatus.OK, "holding" if self.planner.goal is None else "tracking goal", values)


def main(argv=None) -> int:
    return run(PlannerService, argv)
