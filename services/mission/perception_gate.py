"""The perception gate (requirements MIS-1, VIO-3): the perception service turns VIO health into
perception/health's `overall_healthy` (true iff VIO TRACKING). When perception is required (the
mission's `require_vio`, else `require_perception`): unhealthy, or no perception/health for
`perception_timeout_s`, while EXECUTING -> HOLDING (PERCEPTION_LOST); healthy again -> EXECUTING at
the same waypoint (PERCEPTION_RECOVERED); not back within `perception_recovery_s` -> RTL
(PERCEPTION_TIMEOUT). A takeoff waits in HOLDING the same way before starting the mission.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

from .states import Event as E, HoldReason, State


class PerceptionGate:
    """perception/health -> PERCEPTION_LOST / PERCEPTION_RECOVERED / PERCEPTION_TIMEOUT."""

    perception_healthy: bool
    perception_rx_s: float | None

    def on_perception(self, healthy: bool, now_s: float) -> None:
        self.perception_healthy = healthy
        self.perception_rx_s = now_s

    def perception_required(self) -> bool:
        if self.mission is not None and self.mission.require_vio is not None:
            return self.mission.require_vio
        return self.cfg.require_perception

    def _gate_perception(self, now_s: float) -> None:
        """(tick) A silent perception/health is unhealthy; hold, resume or RTL on it."""
        if self.perception_rx_s is not None and now_s - self.perception_rx_s > self.cfg.perception_timeout_s:
            self.perception_healthy = False
        if not self.perception_required():
            return
        if self.state == State.EXECUTING and not self.perception_healthy:
            self.fire(E.PERCEPTION_LOST, "perception unhealthy: holding")
        elif self.state == State.HOLDING and self.hold_reason == HoldReason.PERCEPTION and not self.outage:
            if self.perception_healthy:
                self.fire(E.PERCEPTION_RECOVERED, "perception recovered: resuming" if self.wp_index >= 0
                          else "perception healthy: starting mission")
            elif now_s - self.hold_since_s > self.cfg.perception_recovery_s:
                self.fire(E.PERCEPTION_TIMEOUT, "perception lost > recovery time: RTL")
