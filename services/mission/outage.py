"""fmu or planner outage (ARCHITECTURE §8): state/vehicle stale, fmu's or the planner's liveliness
token gone, or the FC link lost -> HOLDING. When fresh state is back the mission resumes only if
`resume_after_outage` (default: stay HOLDING until commanded) and the FC is holding or in
OFFBOARD, never out of a failsafe RTL/LAND. A stale state that comes back with the next stamp in
sequence was late, not missing (fmu kept publishing; a CPU or transport stall delayed it): that
hold resumes by itself under the same conditions. A stalled mission process is not an outage.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.schemas import VehicleState

from .states import Event as E, HoldReason, State


@dataclass
class Outage:
    """An outage in progress."""

    reason: str                 # what is out, as reported ("fmu outage (fmu not alive)")
    from_state: State           # the state it began in (only EXECUTING resumes by itself)
    stamp_ns: int = 0           # newest state/vehicle stamp when it went stale (0: another outage)


class OutageWatch:
    """fmu / planner liveliness and state/vehicle freshness -> an Outage, and its end."""

    fmu_outage: Outage | None
    fmu_alive: bool
    planner_alive: bool             # unknown until its token is seen: assume up
    awake_since_s: float | None     # when this process last resumed from a stall of its own

    @property
    def outage(self) -> str | None:
        """Why we are in an fmu (or planner) outage, None when not."""
        return self.fmu_outage.reason if self.fmu_outage else None

    def on_fmu_alive(self, alive: bool, now_s: float) -> None:
        """fmu's liveliness token (aero/alive/<vehicle>/fmu) came or went."""
        self.now_s = now_s
        self.fmu_alive = alive
        if not alive:
            self._outage_begins("fmu outage (fmu not alive)")

    def on_planner_alive(self, alive: bool, now_s: float) -> None:
        """The planner's liveliness token came or went (ARCHITECTURE §8: after a planner outage
        the vehicle holds until the mission has re-checked it; fmu brakes meanwhile). The same
        outage path as fmu's: HOLDING, resumed only by START or resume_after_outage."""
        self.now_s = now_s
        self.planner_alive = alive
        if not alive:
            self._outage_begins("planner outage (planner not alive)")
        elif self.outage and self.fmu_alive and self.vehicle is not None \
                and now_s - self.vehicle_rx_s < self.cfg.vehicle_timeout_s:
            self._outage_ends()

    def _late_not_missing(self, st: VehicleState) -> bool:
        """The state went stale, but the next one carries the next stamp: fmu kept publishing and
        the samples were only late (a CPU or transport stall between fmu and us), not an outage."""
        stale_at = self.fmu_outage.stamp_ns if self.fmu_outage else 0
        return bool(stale_at and st.header.stamp_ns
                    and st.header.stamp_ns - stale_at < self.cfg.vehicle_timeout_s * 1e9)

    def _check_vehicle_age(self, now_s: float, stalled: bool) -> None:
        """(tick) No state/vehicle for vehicle_timeout_s of this process's own running time is an
        fmu outage. `stalled` (this process itself stopped: CPU, GIL, SIGSTOP) restarts that time:
        the samples fmu sent meanwhile are queued, and a loaded host can take more than one tick
        to deliver them, so only a full vehicle_timeout_s awake without one is an outage."""
        if stalled:
            self.awake_since_s = now_s
        if self.vehicle_rx_s is None or self.outage:
            return
        silent_s = now_s - max(self.vehicle_rx_s, self.awake_since_s or 0.0)
        if silent_s > self.cfg.vehicle_timeout_s:
            self._outage_begins(f"fmu outage (no state/vehicle for {now_s - self.vehicle_rx_s:.1f} s)",
                                stamp_ns=self.vehicle.header.stamp_ns if self.vehicle else 0)

    def _outage_begins(self, why: str, stamp_ns: int = 0) -> None:
        if self.outage:
            return
        self.fmu_outage = Outage(why, self.state, stamp_ns)
        self.log("outage", reason=why, state=self.state.value)
        if not self.fire(E.FMU_OUTAGE, f"{why}: holding"):
            if self.state != State.IDLE:
                self.message = f"{why} ({self.state.value} continues: the flight controller flies on its own)" \
                    if self.state == State.LAND else f"{why}: holding"

    def _outage_ends(self, late_not_missing: bool = False) -> None:
        """`late_not_missing`: the stale state came back without a gap in its stamps (it was late)."""
        was, self.fmu_outage = self.fmu_outage, None
        self.log("outage_over", reason=was.reason, state=self.state.value, late_not_missing=late_not_missing)
        if self.state != State.HOLDING:
            return
        mode = self.vehicle.flight_mode if self.vehicle else ""
        if ((self.cfg.resume_after_outage or late_not_missing) and was.from_state == State.EXECUTING
                and self.hold_reason == HoldReason.OUTAGE and self.mission is not None
                and mode in ("", "OFFBOARD", "HOLD")):
            # never out of a failsafe RTL/LAND the FC chose: only from its hold (or our OFFBOARD)
            self.fire(E.OUTAGE_RESUME, "state/vehicle was late, not missing (no gap in fmu's stamps): resuming"
                      if late_not_missing else "fmu back after an outage: resuming (resume_after_outage)")
        else:
            self.message = "fmu back after an outage: holding until commanded (START resumes)"
