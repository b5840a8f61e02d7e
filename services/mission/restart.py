"""Persistence and restart: what a mission service restarted mid-flight needs (the mission, its
progress, the state it was in), and how the first vehicle state after a restart decides the FSM
state: flying -> HOLDING ("mission restarted in flight"), on the ground -> IDLE with the
interrupted mission still loaded. Until that state arrives (at most restore_timeout_s) commands
wait. A completed mission is never persisted, a corrupt one never resumed.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from aeroperception.schemas import VehicleState, parse_mission

from .states import Event as E, State


@dataclass
class PendingRestore:
    """restore() was called: the first connected vehicle state rebuilds the FSM state."""

    was: str                        # the state the previous run persisted
    deadline_s: float | None        # commands wait until then (None: no longer)
    note: str = ""                  # what restore() dropped (a completed mission)


class Restart:
    """snapshot() / restore() and the rebuild on the first vehicle state."""

    pending_restore: PendingRestore | None
    on_persist: Callable[[dict], None]

    def snapshot(self) -> dict:
        """What a service restarted mid-flight needs: the mission, its progress and the state we
        were in. On the ground (IDLE) nothing: a new stack after a landed (or finished) flight
        must not come up with the old mission loaded; the mission stays loaded in this process."""
        flying = self.state != State.IDLE and self.mission is not None
        return {"mission_json": self.mission.to_json() if flying else None,
                "wp_index": self.wp_index if flying else -1, "state": self.state.value,
                "start_requested": self.start_requested and flying}

    def _persist(self) -> None:
        self.on_persist(self.snapshot())

    def restore(self, snapshot: dict | None, now_s: float) -> None:
        """Start from what a previous run persisted; the first connected vehicle state decides
        the FSM state (see _rebuild). Until then (at most restore_timeout_s) commands wait."""
        self.now_s = now_s
        pending = self.pending_restore = PendingRestore((snapshot or {}).get("state", "IDLE"),
                                                        now_s + self.cfg.restore_timeout_s)
        text = (snapshot or {}).get("mission_json")
        if text:
            try:
                self.mission = parse_mission(text)
                self.wp_index = int(snapshot.get("wp_index", -1))
            except Exception as e:  # noqa: BLE001 - a bad snapshot must not stop a restart
                self.log("restore_failed", error=str(e))
                self.mission, self.wp_index = None, -1
        if self.mission is not None and self.wp_index >= len(self.mission.waypoints):
            # every waypoint was flown (the landing may have been cut short): nothing to resume
            n = len(self.mission.waypoints)
            pending.note = f"mission {self.mission.mission_id or '(unnamed)'} was complete ({n}/{n} waypoints)"
            self.mission, self.wp_index = None, -1
        self.message = "restarted: waiting for vehicle state to rebuild the mission state"

    def _rebuild(self, st: VehicleState) -> None:
        pending, self.pending_restore = self.pending_restore, None
        was = pending.was
        if self.mission is not None:
            loaded = (f"mission {self.mission.mission_id or '(unnamed)'} loaded at waypoint "
                      f"{max(self.wp_index, 0) + 1}/{len(self.mission.waypoints)}")
        else:
            loaded = f"{pending.note}; no mission loaded" if pending.note else "no mission loaded"
        if self.in_air():
            mode = st.flight_mode or "unknown mode"
            self.expected_mode = "OFFBOARD" if st.flight_mode == "OFFBOARD" else None
            self.mode_confirmed = self.expected_mode is not None
            self.fire(E.RESTARTED_IN_AIR, f"mission restarted in flight (was {was}, flight controller in {mode}): "
                                          f"holding; {loaded}; LAND, RTL or START to resume")
        else:
            self.message = f"mission restarted on the ground (was {was}); {loaded}"
            self._persist()
        self.log("rebuilt", was=was, state=self.state.value, armed=st.armed,
                 landed_state=st.landed_state, mode=st.flight_mode)

    def restoring(self) -> bool:
        """Commands wait: restored, no vehicle state yet, and the restore deadline not passed."""
        p = self.pending_restore
        return p is not None and p.deadline_s is not None and self.now_s < p.deadline_s

    def _check_restore_deadline(self, now_s: float) -> None:
        """(tick) No vehicle state by the deadline: stop refusing commands, say why; the rebuild
        still happens on the first state."""
        p = self.pending_restore
        if p is not None and p.deadline_s is not None and now_s >= p.deadline_s:
            p.deadline_s = None
            self.message = "restarted: no vehicle state yet (is fmu running?)"
