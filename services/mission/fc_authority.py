"""The flight controller has the last word (ARCHITECTURE §8): the mission's requests to it (arm,
disarm, a mode) and their answers, and what the mission does when the FC leaves the mode it asked
for on its own (a failsafe, an RC pilot, another ground station): hold, never fight it.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

from aeroperception.schemas import VehicleState

from .requests import FcRequest, Outcome
from .states import Event as E, HoldReason, State


class FcAuthority:
    """Requests to the flight controller and watching that it stays in the mode we asked for."""

    expected_mode: str | None       # the FC mode we asked for last
    mode_confirmed: bool            # ... and the FC has been seen in it

    def _request_mode(self, mode: str, outcome: Outcome | None = None) -> None:
        """Ask the FC for `mode`; `outcome` (if given) is settled by the FC's answer."""
        self.expected_mode, self.mode_confirmed = mode, False
        self._ask_fc(FcRequest(mode, outcome, "mode"))

    def _ask_fc(self, req: FcRequest) -> None:
        """Send `req` over the bridge; its answer comes back to _on_fc_answer."""
        def answer(ok: bool, message: str) -> None:
            self._on_fc_answer(req, ok, message)
        if req.call in ("arm", "disarm"):
            self.bridge.arm(req.call == "arm", answer)
        else:
            self.bridge.set_mode(req.call, answer)

    def _on_fc_answer(self, req: FcRequest, ok: bool, message: str) -> None:
        """The flight controller answered `req`: settle its outcome; a refused mode is the ERROR
        path (in the air: hold; on the ground: IDLE); a granted arming for TAKEOFF takes off."""
        outcome = req.outcome or Outcome()
        if req.then == "takeoff":
            self.takeoff_pending = False
            if not ok:
                self.start_requested = False
                outcome.settle(False, f"arming failed: {message}")
                self.message = f"arming failed: {message}"
            elif self.fire(E.TAKEOFF_CMD, "taking off"):
                outcome.settle(True, "taking off")
            else:
                outcome.settle(False, f"takeoff not possible in {self.state.value}")
        elif req.then != "mode":
            outcome.settle(ok, message)
        elif ok:
            outcome.settle(True, self.message)
        else:
            what = req.call
            self.log("bridge_failed", call=what, message=message)
            event = E.BRIDGE_FAILED_AIR if self.in_air() else E.BRIDGE_FAILED_GROUND
            if not self.fire(event, f"{what} failed: {message}"):
                self.message = f"{what} failed: {message}"
            outcome.settle(False, f"{what} failed: {message}")

    def _watch_fc_mode(self, st: VehicleState) -> None:
        """The FC left the mode we asked for without being asked: never fight it. Not when it
        disarms: PX4 then switches to the last mode it can arm in (after a LAND that ends in
        OFFBOARD), which flies nothing and is no takeover."""
        mode = st.flight_mode
        if not mode or self.expected_mode is None or not st.armed:
            return
        landing = self.state == State.LAND and self.expected_mode in ("LAND", "RTL")
        ours = ("LAND", "RTL") if landing else (self.expected_mode,)
        if mode in ours:
            self.mode_confirmed = True
            return
        if not self.mode_confirmed:
            return  # our request is not confirmed yet (heartbeats lag): nothing to judge
        self.expected_mode, self.mode_confirmed = None, False
        reason = f"flight controller switched to {mode}"
        self.log("fc_mode_changed", mode=mode, state=self.state.value)
        if not self.fire(E.FC_MODE_CHANGED, f"{reason}: holding, not commanding motion; START resumes"):
            if self.state == State.HOLDING:
                self.hold_reason = HoldReason.FLIGHT_CONTROLLER
                self.message = f"{reason}; holding, START resumes"
