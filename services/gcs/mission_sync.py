"""The stack's mission as ground stations see it through the mission protocol: an upload is
converted and loaded into the mission service, a mission loaded some other way (aero mission
load/fly) is fetched and served as items, a jump (MISSION_SET_CURRENT) moves the mission, and
mission/status + mission/waypoint_reached become MISSION_ITEM_REACHED / MISSION_CURRENT.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import MissionStatus, SchemaError, WaypointReached, parse_mission
from aeroperception.services.runtime import CallError

from .home import Home
from .mission_items import Item, MissionConversionError, convert_items, mission_to_items
from .mission_progress import Progress
from .mission_protocol import MissionProtocol
from .mission_speed import SPEED_DEFAULT, waypoint_speeds
from .ops import SPEED_PARAM, SPEED_SERVICE, Outcome, StackOps
from .params import ParamTable
from .telemetry import TelemetryState

FETCH_RETRY_S = 5.0
Notify = Callable[..., None]   # notify(text, peer or None, severity=CRITICAL): a STATUSTEXT


class MissionSync:
    """Owns the mission protocol (`protocol`) and the progress report (`progress`, shared with
    telemetry as tel.progress) and keeps both in step with the mission service.

    home(): the home in force; send(msg, broadcast=...): to ground stations.
    """

    def __init__(self, ops: StackOps, progress: Progress, tel: TelemetryState, table: ParamTable,
                 home: Callable[[], Home], send: Callable[..., None], notify: Notify, log: Any, *,
                 item_timeout_s: float, retries: int, max_items: int):
        self.ops, self.progress, self.tel, self.table = ops, progress, tel, table
        self.home, self.send, self.notify, self.log = home, send, notify, log
        self.protocol = MissionProtocol(send, self.load, item_timeout_s, retries, max_items, log=log.warn,
                                        notify=notify)
        # (mission_id, waypoints) of the mission our items describe; one loaded some other way
        # (aero mission load/fly) is fetched from mission/srv/get so a download shows it.
        self.synced: tuple[str, int] | None = None
        self.fetching = False
        self.fetch_failed_s = -math.inf
        self.loads = 0
        self._last_progress: tuple[int, int] = (0, 0)
        self._held_reason: str | None = None  # the mission's last HOLDING reason told to ground stations

    @property
    def upload_under_way(self) -> bool:
        t = self.protocol.transfer
        return self.protocol.loading or (t is not None and t.direction == "upload")

    @property
    def busy(self) -> bool:
        return self.protocol.loading or self.protocol.transfer is not None

    def sync_plan(self) -> None:
        self.tel.mission_total = len(self.protocol.items)
        self.tel.mission_id = self.protocol.plan_id

    # ------------------------------------------------------------ ground station -> stack

    def load(self, items: list[Item], done: Callable[[bool, str, int], None]) -> None:
        """A complete upload: converted about the home in force and loaded into the mission service."""
        default_alt = self.table.find("mission", "takeoff_altitude_m")
        # PX4: an item without an acceptance radius (param2 0) uses NAV_ACC_RAD (the planner's)
        radius = self.table.find("planner", "acceptance_radius_m")
        self.loads += 1
        try:
            mission, seqs = convert_items(items, self.home(), mission_id=f"gcs-{self.loads}",
                                          default_takeoff_m=float(default_alt[1].value) if default_alt else 3.0,
                                          acceptance_radius_m=float(radius[1].value) if radius else 0.5)
        except MissionConversionError as e:
            done(False, str(e), e.result)
            return
        speeds = waypoint_speeds(items, seqs)
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        if found is not None:
            lo, hi = found[1].min, found[1].max
            for v in speeds:
                if v is not None and v != SPEED_DEFAULT and ((lo is not None and v < lo) or (hi is not None and v > hi)):
                    done(False, f"DO_CHANGE_SPEED {v} m/s outside {found[1].mav_name} [{lo}, {hi}]",
                         M.MAV_MISSION_INVALID_PARAM2)
                    return

        def loaded(res: Any) -> None:
            if isinstance(res, CallError):
                done(False, str(res), M.MAV_MISSION_ERROR)
                return
            if res.success:
                self.progress.load(mission.mission_id, items, seqs)
                self.ops.new_mission_speeds(speeds, mission.mission_id)
                self.synced = (mission.mission_id, len(mission.waypoints))
            done(res.success, res.message, M.MAV_MISSION_DENIED)   # accepts the items: the new plan id
            if res.success:
                # total and plan id together, once the items are in: MISSION_CURRENT streamed in
                # between carried the new total with the old plan id (0 after a first upload)
                self.sync_plan()
                self.tel.mission_seq = 0

        self.ops.load_mission(mission.to_json(), loaded)

    def set_current(self, seq: int) -> bool:
        """MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: the mission jumps (flies to that item
        next, as PX4 does), not only MISSION_CURRENT; a refusal by the mission is a STATUSTEXT."""
        k = self.progress.waypoint_for(seq)
        ok = k is not None and self.protocol.set_current(seq)
        if ok:
            def done(outcome: Outcome) -> None:
                if not outcome.ok:
                    self.notify(f"Mission jump to item {seq} refused: {outcome.message}", None)
            self.ops.jump_to(k, done)
            self.progress.set_current(seq)
            self.tel.mission_seq = seq
        return ok

    # ------------------------------------------------------------ stack -> ground stations

    def on_status(self, msg: MissionStatus) -> None:
        held = msg.message if msg.state == MissionStatus.STATE_HOLDING else None
        if held and held != self._held_reason:
            # why the mission holds (an unreachable waypoint, a failsafe, ...), once per reason
            self.notify(f"Mission HOLDING: {held}", None, M.MAV_SEVERITY_WARNING)
        self._held_reason = held
        self.tel.mission = msg
        if msg.mission_id and (msg.mission_id, msg.total_waypoints) != self.synced:
            self._fetch()
        self._report(self.progress.on_status(msg.mission_id, msg.state, msg.active_waypoint, msg.total_waypoints))
        self.sync_plan()
        self.ops.observe_mission(msg)

    def on_reached(self, msg: WaypointReached) -> None:
        self._report(self.progress.on_reached(msg.mission_id, msg.index))
        if msg.mission_id == self.ops.speeds.mission_id:
            self.ops.apply_mission_speed(msg.index + 1)         # the speed for the next leg, at once

    def _report(self, reached: list[int]) -> None:
        """MISSION_ITEM_REACHED for each seq, to every ground station; MISSION_CURRENT at once when
        the current item or the mission state changed (as PX4 sends it on change)."""
        for seq in reached:
            self.send(M.MAVLink_mission_item_reached_message(seq), broadcast=True)
        if 0 <= self.progress.current < len(self.protocol.items):
            self.protocol.current = self.progress.current
        now = (self.progress.current, self.progress.state)
        if reached or now != self._last_progress:
            self._last_progress = now
            self.sync_plan()
            self.send(self.tel.mission_current(), broadcast=True)

    def _fetch(self) -> None:
        """The mission service has a mission we did not upload: fetch it (mission/srv/get) and
        serve it as items (NAV_TAKEOFF + NAV_WAYPOINTs, see mission_items.mission_to_items). Not
        while a transfer is under way; a failed fetch is retried after FETCH_RETRY_S."""
        if self.fetching or self.busy or time.monotonic() - self.fetch_failed_s < FETCH_RETRY_S:
            return
        self.fetching = True

        def done(res: Any) -> None:
            self.fetching = False
            if isinstance(res, CallError) or not res.success:
                self.fetch_failed_s = time.monotonic()
                return
            key = (res.mission_id, res.num_waypoints)
            if key == self.synced or self.busy:
                return   # ours (an upload overtook the status), or busy: the next status retries
            try:
                mission = parse_mission(res.mission_json)
            except SchemaError as e:
                self.fetch_failed_s = time.monotonic()
                self.log.warn("mission_fetch_invalid", error=str(e))
                return
            self.protocol.items = mission_to_items(mission, self.home())
            self.protocol.current = 0
            self.progress.load(mission.mission_id, self.protocol.items,
                               list(range(1, len(mission.waypoints) + 1)))   # item 0 is the takeoff
            self.sync_plan()
            self.ops.new_mission_speeds([], mission.mission_id)
            self.tel.mission_seq = 0
            self.synced = key
            self.log.info("mission_synced", mission_id=mission.mission_id, items=len(self.protocol.items))

        self.ops.get_mission(done)
