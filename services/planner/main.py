"""Process shell: state + goal from Zenoh, 50 Hz setpoints out."""
from __future__ import annotations

import math
import time

from aeroperception.schemas import (
    DiagnosticStatus, Header, PoseStamped, TrajectoryStatus, VehicleState, WaypointReached,
)
from aeroperception.services.runtime import Health, Service, run

from . import contract
from .logic import Goal, WaypointPlanner


class PlannerService(Service):
    """50 Hz waypoint planner (seed 000 §5.2)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS

    def start(self) -> None:
        p = self.params
        self.planner = WaypointPlanner(p.max_velocity_mps, p.kp, p.acceptance_radius_m)
        self.params.on_change(self._on_param)
        self.state: VehicleState | None = None
        self.state_rx_s = 0.0
        self.last_distance: float | None = None
        self.goal_msg: PoseStamped | None = None
        self.goals_received = 0
        self.pub_sp = self.node.publisher("fmu/in/trajectory_setpoint", contract.OUTPUTS["fmu/in/trajectory_setpoint"],
                                          express=True)
        self.pub_status = self.node.publisher("planner/status", TrajectoryStatus)
        self.pub_reached = self.node.publisher("planner/waypoint_reached", WaypointReached)
        self.node.subscribe("state/vehicle", VehicleState, self._on_state)
        self.node.subscribe("mission/active_goal", PoseStamped, self._on_goal, strict=True)
        self.last_pub_s = 0.0
        self.loop = self.node.every(1.0 / p.rate_hz, self._tick, name="setpoint")
        self.node.every(0.1, self._publish_status, name="status")

    def _on_param(self, name, value) -> None:
        if name in ("max_velocity_mps", "kp", "acceptance_radius_m"):
            setattr(self.planner, name, value)
        elif name == "rate_hz":
            self.loop.set_rate(value)

    def _on_state(self, msg: VehicleState) -> None:
        self.state, self.state_rx_s = msg, time.monotonic()
        self._cycle()  # event-driven: a fresh state goes out as a setpoint at once (hot path)

    def _tick(self) -> None:
        """The 50 Hz deadline loop: guarantees the rate when state arrives slower or late."""
        if time.monotonic() - self.last_pub_s > 1.25 * self.loop.period_s:
            self._cycle()

    def _on_goal(self, msg: PoseStamped) -> None:
        if msg == self.goal_msg:
            return  # mission re-publishes its latest goal at 2 Hz for late joiners: already applied
        self.goal_msg = msg
        if msg.header.frame_id == contract.HOLD_FRAME:
            self.planner.set_goal(None)
            return
        q = msg.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        self.goals_received += 1
        self.planner.set_goal(Goal(msg.pose.position.to_array(), yaw, self.goals_received))

    def state_fresh(self) -> bool:
        return self.state is not None and time.monotonic() - self.state_rx_s < self.params.state_timeout_s

    def _cycle(self) -> None:
        if not self.state_fresh():
            return  # no state: send nothing; fmu holds on its own after 100 ms of silence
        st = self.state
        res = self.planner.step(st.position_m.to_array(), st.yaw_rad)
        res.setpoint.header = Header(stamp_ns=st.header.stamp_ns, frame_id="map")
        self.pub_sp.publish(res.setpoint)
        self.last_pub_s = time.monotonic()
        self.last_distance = res.distance_m
        if res.reached and self.planner.goal is not None:
            g = self.planner.goal
            self.pub_reached.publish(WaypointReached(header=self.node.header("map"), index=g.index,
                                                     position_m=st.position_m))
            self.log.info("waypoint_reached", index=g.index, distance_m=round(res.distance_m, 3))

    def _publish_status(self) -> None:
        status = self.planner.status if self.state_fresh() else TrajectoryStatus.STATUS_ERROR
        self.pub_status.publish(TrajectoryStatus(
            header=self.node.header("map"), status=status,
            trajectory_id=f"goal-{self.goals_received}",
            position_error_m=self.last_distance or 0.0))

    def health(self) -> Health:
        if not self.state_fresh():
            return Health(DiagnosticStatus.ERROR, "no fresh state/vehicle: not publishing setpoints")
        return Health(DiagnosticStatus.OK, "holding" if self.planner.goal is None else "tracking goal",
                      {"distance_m": self.last_distance if self.last_distance is not None else "n/a"})


def main(argv=None) -> int:
    return run(PlannerService, argv)
