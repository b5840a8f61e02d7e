"""Mission progress as the MAVLink mission protocol reports it (MISSION_ITEM_REACHED,
MISSION_CURRENT) from the stack's mission/status and mission/waypoint_reached, without Zenoh."""
from __future__ import annotations

from pymavlink.dialects.v20 import common as M

from .mission_items import NAV_POSITION, Item

def takeoff_seq(items: list[Item]) -> int | None:
    """The seq of the NAV_TAKEOFF item a mission starts with (only DO_CHANGE_SPEED before it), or None."""
    for it in items:
        if it.command == M.MAV_CMD_NAV_TAKEOFF:
            return it.seq
        if it.command != M.MAV_CMD_DO_CHANGE_SPEED:
            return None
    return None


class Progress:
    """The mission-progress side of the MAVLink mission protocol for the mission our items describe
    (`mission_id`), from the stack's mission/status and mission/waypoint_reached:

    - MISSION_ITEM_REACHED (the seqs returned by on_status / on_reached) for every item, in order,
      once per run: the NAV_TAKEOFF item when the takeoff is done (the mission goes on to its first
      waypoint), each waypoint's item when it is reached, the DO items after an item as soon as
      that item is reached (they run right away), and a terminal NAV_LAND item without a position
      once the vehicle has landed (IDLE). A NAV_RETURN_TO_LAUNCH item is never reported reached,
      as PX4 hands the vehicle over to return mode there (MAVSDK counts on that).
    - MISSION_CURRENT (`current`, `state`, `mode`): the item being flown to, mission_state
      NOT_STARTED / ACTIVE / PAUSED / COMPLETE, mission_mode 1 (in mission) or 2 (suspended); once
      complete, seq = total (the number of items), as the spec says ("on last item, sequence ==
      total") and MAVSDK's progress reaches N/N.

    A run starts when the mission leaves IDLE (or starts again after completing) and ends landed.
    A run stopped before its end (HOLD, LAND/RTL commanded, landed early) is PAUSED at its item."""

    RUNNING = ("TAKEOFF", "EXECUTING")

    def __init__(self) -> None:
        self.mission_id = ""
        self.items: list[Item] = []
        self.wp_seqs: list[int] = []          # the item seq of each mission waypoint
        self.takeoff_seq: int | None = None
        self.land_seq: int | None = None      # a terminal NAV_LAND without a position: reached when landed
        self.rtl_seq: int | None = None       # a terminal NAV_RETURN_TO_LAUNCH: never reported reached
        self.last_seq = -1                    # the last item flown (items after a LAND/RTL are not)
        self._reset_run()
        self.current = 0
        self.prev_state = ""

    def _reset_run(self) -> None:
        self.upto = -1                        # the highest seq reported reached in this run
        self.state = M.MISSION_STATE_NOT_STARTED if self.items else M.MISSION_STATE_NO_MISSION
        self.mode = 0
        self.started = False
        self.done = False                     # every waypoint reached (the landing may follow)

    def load(self, mission_id: str, items: list[Item], wp_seqs: list[int]) -> None:
        self.mission_id, self.items, self.wp_seqs = mission_id, list(items), list(wp_seqs)
        self.takeoff_seq = takeoff_seq(items)
        self.land_seq = self.rtl_seq = None
        self.last_seq = len(items) - 1
        for it in items:
            if it.command in (M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH):
                self.last_seq = it.seq
                if it.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                    self.rtl_seq = it.seq
                elif it.seq not in self.wp_seqs:
                    self.land_seq = it.seq
                break
        self._reset_run()
        self.current = 0
        self.prev_state = ""

    def set_current(self, seq: int) -> None:
        self.current = seq

    def waypoint_for(self, seq: int) -> int | None:
        """The mission waypoint (0-based) a jump to item `seq` flies to next: the item's own
        waypoint, or the first one after it (a takeoff or DO item); None past the last one."""
        return next((k for k, s in enumerate(self.wp_seqs) if s >= seq), None)

    @property
    def total(self) -> int:
        return len(self.items)

    # ------------------------------------------------------------ events

    def _reach(self, seq: int) -> list[int]:
        """Report every item up to seq (and the DO items right after it)."""
        end = seq
        while end + 1 <= self.last_seq and self.items[end + 1].command not in NAV_POSITION | {
                M.MAV_CMD_NAV_RETURN_TO_LAUNCH}:
            end += 1
        out = [s for s in range(self.upto + 1, end + 1) if s != self.rtl_seq]
        self.upto = max(self.upto, end)
        if self.upto + 1 <= self.last_seq:
            self.current = self.upto + 1
        return out

    def _complete(self) -> list[int]:
        out = self._reach(self.last_seq)
        self.state, self.mode, self.current = M.MISSION_STATE_COMPLETE, 2, self.total
        return out

    def _takeoff(self) -> list[int]:
        if self.takeoff_seq is None or self.upto >= self.takeoff_seq:
            return []
        return self._reach(self.takeoff_seq)

    def on_status(self, mission_id: str, state: str, active_waypoint: int = -1, total_waypoints: int = 0) -> list[int]:
        if not mission_id or mission_id != self.mission_id or not self.items:
            self.prev_state = ""
            return []
        prev, self.prev_state = self.prev_state, state
        complete = self.state == M.MISSION_STATE_COMPLETE
        if state in self.RUNNING and (prev in ("", "IDLE", "LAND") or (complete and prev == "HOLDING"
                                                                          and state == "EXECUTING")):
            self._reset_run()                     # a new run
            self.started = True
        if not self.started:
            return []
        out: list[int] = []
        waypoints_done = total_waypoints > 0 and active_waypoint >= total_waypoints
        if waypoints_done and not self.done:
            self.done = True
            out += self._reach(self.wp_seqs[-1]) if self.wp_seqs else []
        if self.state == M.MISSION_STATE_COMPLETE:
            return out
        if self.done:
            if self.land_seq is None or state == "IDLE":
                return out + self._complete()
            self.state, self.mode, self.current = M.MISSION_STATE_ACTIVE, 1, self.land_seq   # landing: its item
            return out
        if state == "EXECUTING":
            out += self._takeoff()
            self.state, self.mode = M.MISSION_STATE_ACTIVE, 1
            if 0 <= active_waypoint < len(self.wp_seqs):
                self.current = self.wp_seqs[active_waypoint]
        elif state == "TAKEOFF":
            self.state, self.mode = M.MISSION_STATE_ACTIVE, 1
            if self.takeoff_seq is not None:
                self.current = self.takeoff_seq
        else:                                     # HOLDING, LAND or IDLE before the end: paused
            self.state, self.mode = M.MISSION_STATE_PAUSED, 2
        return out

    def on_reached(self, mission_id: str, index: int) -> list[int]:
        if not mission_id or mission_id != self.mission_id or not 0 <= index < len(self.wp_seqs):
            return []
        if self.state == M.MISSION_STATE_COMPLETE and self.prev_state == "IDLE":
            self._reset_run()                     # a new run whose first status has not come yet
        self.started = True
        out = self._takeoff() + self._reach(self.wp_seqs[index])
        if index == len(self.wp_seqs) - 1:
            self.done = True
            if self.land_seq is None:
                out += self._complete()
            else:
                self.current = self.land_seq
        return out
