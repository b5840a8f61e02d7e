"""MAVLink mission items <-> the stack's Mission (ENU about home), and the mission protocol state
machine (upload, download, clear, set current) for mission_type 0, without Zenoh.

Conversion. Geodetic <-> local ENU about home (`Home`: lat, lon, alt AMSL, and where home is in
the local frame: the flight controller's HOME_POSITION, else the gcs parameters with home at the
local origin); the projection is PX4's (services/mavlink/geo.py) and every NED<->ENU step goes
through services/mavlink/frames.py.
Accepted items: NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, NAV_RETURN_TO_LAUNCH, DO_CHANGE_SPEED in
frames GLOBAL[_INT] (AMSL), GLOBAL_RELATIVE_ALT[_INT], LOCAL_NED, LOCAL_ENU. A takeoff item sets
the mission's takeoff altitude; LAND adds its position (when it has one) and ends the mission;
RTL flies back above home. Yaw (param4, NED heading deg, NaN = keep) becomes ENU yaw_deg.
A waypoint at or below home altitude is refused (MAV_MISSION_INVALID_PARAM7, naming the item), in
every frame alike: global-relative z <= 0, AMSL z <= home's altitude (issue 8 #5: an AMSL item at
home altitude had become a waypoint at ground level), local z at or below home's; NAV_LAND and RTL
items are exempt. (The mission service's geofence floor applies on top.)

Plan id. `plan_id(items)` is a CRC-32 of the items (never 0: 0 means "no mission"); gcs reports
it as MISSION_CURRENT.mission_id and in MISSION_ACK / MISSION_COUNT opaque_id (MAVLink extension
fields, see messages.py), so a ground station notices that the mission on the vehicle changed.

Speed. The stack's Mission (seed 000 JSON) has no speed, so DO_CHANGE_SPEED items do not go into
it: the planner's live speed limit (planner max_velocity_mps, PLN_MAX_VELOCITY) is the speed.
`waypoint_speeds` gives, per mission waypoint, the speed in force while flying to it (the last
DO_CHANGE_SPEED item before it; None = none yet, leave the planner's speed alone), and gcs applies
it (SpeedSchedule) when the mission starts or resumes at that waypoint and when the previous one
is reached. Speed types 0 (air) and 1 (ground) both set it (a multicopter in still air); 2/3
(climb/descent) are accepted and ignored (the planner has one 3-D limit). param2 -1 (or NaN) is
"no change", -2 "back to the planner's default".
Mission-scoped (issue 9 #7): a speed set for a mission (its DO_CHANGE_SPEED items, or a
DO_CHANGE_SPEED command while it flies) ends with the mission: the planner's speed from before
is restored when the mission completes (last waypoint reached), lands (LAND/RTL, aborted or not),
is IDLE again, or is replaced by another mission. A pause (HOLDING) keeps it. A DO_CHANGE_SPEED
command outside a mission stays in force (PLN_MAX_VELOCITY / MPC_XY_VEL_MAX show it).
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import Mission, Waypoint
from aeroperception.services.mavlink import frames
from aeroperception.services.mavlink.geo import MapProjection

from .messages import MissionAck, MissionCount, statustext

M = mavlink
GLOBAL_FRAMES = {M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT}
RELATIVE_FRAMES = {M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
LOCAL_FRAMES = {M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_ENU}
NAV_POSITION = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND}
SUPPORTED_COMMANDS = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND,
                      M.MAV_CMD_NAV_RETURN_TO_LAUNCH, M.MAV_CMD_DO_CHANGE_SPEED}
SPEED_TYPES_HORIZONTAL = (0, 1)     # DO_CHANGE_SPEED param1: airspeed, ground speed
SPEED_TYPES_VERTICAL = (2, 3)       # climb, descent speed: no separate limit here
SPEED_NO_CHANGE = -1.0
SPEED_DEFAULT = -2.0


def change_speed_value(speed_type: float, speed: float) -> float | None:
    """DO_CHANGE_SPEED (param1, param2) -> the planner speed it asks for: m/s > 0, SPEED_DEFAULT,
    or None (no change: -1, NaN, or a vertical speed type). ValueError(param index, reason) if
    invalid."""
    if not math.isfinite(speed_type) or int(speed_type) != speed_type or \
            int(speed_type) not in SPEED_TYPES_HORIZONTAL + SPEED_TYPES_VERTICAL:
        raise ValueError(1, f"speed type {speed_type} not supported")
    if int(speed_type) in SPEED_TYPES_VERTICAL:
        return None
    if not math.isfinite(speed) or speed == SPEED_NO_CHANGE:
        return None
    if speed == SPEED_DEFAULT:
        return SPEED_DEFAULT
    if speed <= 0:
        raise ValueError(2, f"speed {speed} m/s must be > 0 (or -1 no change, -2 default)")
    return float(speed)


class MissionConversionError(ValueError):
    """An item we cannot fly, with the MAV_MISSION_RESULT to answer and a readable reason."""

    def __init__(self, result: int, message: str):
        super().__init__(message)
        self.result = result


@dataclass(frozen=True)
class Home:
    """Where the local ENU frame sits on the Earth: home's geodetic position (`alt_m` AMSL) and
    `local_m`, the same point in the local ENU frame (the flight controller's HOME_POSITION
    x/y/z; (0, 0, 0) when home is the local origin, as with the gcs parameters).

    Geodetic <-> local goes through the local origin, as PX4 does it (its MapProjection is about
    the EKF origin, not home): `origin` is the point whose projection puts home at `local_m`.
    Altitudes "relative" are above home (MAVLink relative_alt, global-relative mission frames):
    local z = relative altitude + local_m z.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float  # AMSL
    local_m: tuple[float, float, float] = (0.0, 0.0, 0.0)   # home in the local ENU frame

    @property
    def projection(self) -> MapProjection:
        """The projection about home itself."""
        return MapProjection(self.lat_deg, self.lon_deg)

    @cached_property
    def origin(self) -> MapProjection:
        """The projection about the local origin (home when local_m is zero)."""
        east, north = float(self.local_m[0]), float(self.local_m[1])
        if east == 0.0 and north == 0.0:
            return self.projection
        lat, lon = self.projection.reproject(-north, -east)   # first guess, then fixed-point refinement
        for _ in range(8):
            got_lat, got_lon = MapProjection(lat, lon).reproject(north, east)
            d_lat, d_lon = self.lat_deg - got_lat, (self.lon_deg - got_lon + 180.0) % 360.0 - 180.0
            lat, lon = lat + d_lat, lon + d_lon
            if abs(d_lat) < 1e-12 and abs(d_lon) < 1e-12:
                break
        return MapProjection(lat, (lon + 180.0) % 360.0 - 180.0)

    def local_z(self, alt_rel_m: float) -> float:
        """Altitude above home -> local ENU z."""
        return float(alt_rel_m) + float(self.local_m[2])

    def to_enu(self, lat_deg: float, lon_deg: float, alt_rel_m: float) -> tuple[float, float, float]:
        """Geodetic (altitude above home) -> local ENU metres."""
        north, east = self.origin.project(lat_deg, lon_deg)
        x, y, _ = frames.ned_to_enu([north, east, 0.0])
        return float(x), float(y), self.local_z(alt_rel_m)

    def to_geodetic(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """Local ENU metres -> (lat_deg, lon_deg, altitude above home)."""
        north, east, _ = frames.enu_to_ned([x, y, 0.0])
        lat, lon = self.origin.reproject(float(north), float(east))
        return lat, lon, float(z) - float(self.local_m[2])


@dataclass
class Item:
    """One mission item, frame and command as MAVLink has them; x/y are degrees in global frames
    and metres in local ones (MISSION_ITEM_INT's 1e7 / 1e4 scaling removed)."""

    seq: int
    frame: int
    command: int
    current: int = 0
    autocontinue: int = 1
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0

    @classmethod
    def from_msg(cls, msg) -> "Item":
        """MISSION_ITEM_INT or legacy MISSION_ITEM -> Item."""
        x, y = float(msg.x), float(msg.y)
        if msg.get_type() == "MISSION_ITEM_INT":
            scale = 1e4 if msg.frame in LOCAL_FRAMES or msg.frame == M.MAV_FRAME_LOCAL_OFFSET_NED else 1e7
            x, y = x / scale, y / scale
        return cls(seq=msg.seq, frame=msg.frame, command=msg.command, current=msg.current,
                   autocontinue=msg.autocontinue, param1=msg.param1, param2=msg.param2,
                   param3=msg.param3, param4=msg.param4, x=x, y=y, z=float(msg.z))

    def to_msg_int(self, target_system: int, target_component: int, mission_type: int = 0):
        scale = 1e4 if self.frame in LOCAL_FRAMES else 1e7
        return M.MAVLink_mission_item_int_message(
            target_system, target_component, self.seq, self.frame, self.command, self.current,
            self.autocontinue, self.param1, self.param2, self.param3, self.param4,
            _int32(self.x * scale), _int32(self.y * scale), self.z, mission_type)

    def to_msg_legacy(self, target_system: int, target_component: int, mission_type: int = 0):
        return M.MAVLink_mission_item_message(
            target_system, target_component, self.seq, self.frame, self.command, self.current,
            self.autocontinue, self.param1, self.param2, self.param3, self.param4,
            self.x, self.y, self.z, mission_type)


def _int32(v: float) -> int:
    return max(-2**31, min(2**31 - 1, int(round(v))))


def _has_position(item: Item) -> bool:
    if item.frame in LOCAL_FRAMES:
        return True
    return math.isfinite(item.x) and math.isfinite(item.y) and not (item.x == 0.0 and item.y == 0.0)


def item_to_enu(item: Item, home: Home) -> tuple[float, float, float]:
    """The position of a NAV item in ENU about home."""
    if not all(math.isfinite(v) for v in (item.x, item.y, item.z)):
        raise MissionConversionError(M.MAV_MISSION_INVALID_PARAM5_X, f"item {item.seq}: non-finite position")
    if item.frame in RELATIVE_FRAMES:
        return home.to_enu(item.x, item.y, item.z)
    if item.frame in GLOBAL_FRAMES:
        return home.to_enu(item.x, item.y, item.z - home.alt_m)
    if item.frame == M.MAV_FRAME_LOCAL_NED:
        x, y, z = frames.ned_to_enu([item.x, item.y, item.z])
        return float(x), float(y), float(z)
    if item.frame == M.MAV_FRAME_LOCAL_ENU:
        return item.x, item.y, item.z
    raise MissionConversionError(M.MAV_MISSION_UNSUPPORTED_FRAME,
                                 f"item {item.seq}: frame {item.frame} not supported")


def items_to_mission(items: list[Item], home: Home, mission_id: str = "gcs",
                     default_takeoff_m: float = 3.0, acceptance_radius_m: float = 0.5) -> Mission:
    """MAVLink items -> Mission (raises MissionConversionError naming the item)."""
    return convert_items(items, home, mission_id, default_takeoff_m, acceptance_radius_m)[0]


def convert_items(items: list[Item], home: Home, mission_id: str = "gcs", default_takeoff_m: float = 3.0,
                  acceptance_radius_m: float = 0.5) -> tuple[Mission, list[int]]:
    """MAVLink items -> (Mission, the item seq each mission waypoint came from)."""
    waypoints: list[Waypoint] = []
    seqs: list[int] = []
    takeoff_alt = None
    radius = None
    last_z = default_takeoff_m
    last_yaw = 0.0
    for it in items:
        if it.command not in SUPPORTED_COMMANDS:
            raise MissionConversionError(M.MAV_MISSION_UNSUPPORTED, f"item {it.seq}: command {it.command} not supported")
        if it.command == M.MAV_CMD_DO_CHANGE_SPEED:
            try:
                change_speed_value(it.param1, it.param2)   # applied by gcs: see waypoint_speeds
            except ValueError as e:
                index, reason = e.args
                result = M.MAV_MISSION_INVALID_PARAM1 if index == 1 else M.MAV_MISSION_INVALID_PARAM2
                raise MissionConversionError(result, f"item {it.seq}: {reason}") from None
            continue
        if it.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            waypoints.append(Waypoint(x=home.local_m[0], y=home.local_m[1], z=max(last_z, home.local_z(1.0)),
                                      yaw_deg=last_yaw))
            seqs.append(it.seq)
            break
        if it.frame not in RELATIVE_FRAMES | GLOBAL_FRAMES | LOCAL_FRAMES:
            raise MissionConversionError(M.MAV_MISSION_UNSUPPORTED_FRAME,
                                         f"item {it.seq}: frame {it.frame} not supported")
        if math.isfinite(it.param4):
            last_yaw = math.degrees(frames.yaw_ned_to_enu(math.radians(it.param4)))
        if it.command == M.MAV_CMD_NAV_TAKEOFF:
            x, y, z = item_to_enu(it, home)
            if z - home.local_m[2] <= 0:
                raise MissionConversionError(M.MAV_MISSION_INVALID_PARAM7,
                                             f"item {it.seq}: takeoff altitude {z - home.local_m[2]:.1f} m <= 0")
            takeoff_alt = z
            last_z = z
            continue
        if it.command == M.MAV_CMD_NAV_LAND:
            if _has_position(it):
                x, y, _ = item_to_enu(it, home)
                waypoints.append(Waypoint(x=x, y=y, z=last_z, yaw_deg=last_yaw))
                seqs.append(it.seq)
            break  # the mission manager lands after the last waypoint
        x, y, z = item_to_enu(it, home)
        above_home = z - home.local_m[2]
        if above_home <= 0:
            amsl = f" ({it.z:.1f} m AMSL, home {home.alt_m:.1f} m)" if it.frame in GLOBAL_FRAMES else ""
            raise MissionConversionError(M.MAV_MISSION_INVALID_PARAM7,
                                         f"item {it.seq}: waypoint altitude {above_home:.1f} m is at or below "
                                         f"home{amsl}")
        if it.param2 > 0 and radius is None:
            radius = float(it.param2)
        waypoints.append(Waypoint(x=x, y=y, z=z, yaw_deg=last_yaw))
        seqs.append(it.seq)
        last_z = z
    if not waypoints:
        raise MissionConversionError(M.MAV_MISSION_ERROR, "mission has no waypoint")
    mission = Mission(mission_id=mission_id, takeoff_altitude_m=takeoff_alt or default_takeoff_m,
                      waypoints=waypoints, waypoint_acceptance_radius_m=radius or acceptance_radius_m)
    return mission, seqs


def waypoint_speeds(items: list[Item], seqs: list[int]) -> list[float | None]:
    """Per mission waypoint (seqs: the item each came from, as convert_items returns them), the
    speed asked for by the last DO_CHANGE_SPEED item before it: m/s, SPEED_DEFAULT, or None."""
    out: list[float | None] = []
    speed: float | None = None
    i = 0
    for seq in seqs:
        while i < len(items) and items[i].seq < seq:
            it = items[i]
            if it.command == M.MAV_CMD_DO_CHANGE_SPEED:
                try:
                    v = change_speed_value(it.param1, it.param2)
                except ValueError:
                    v = None
                if v is not None:
                    speed = v
            i += 1
        out.append(speed)
    return out


class SpeedSchedule:
    """When to change the planner's speed for the loaded mission's DO_CHANGE_SPEED items:
    due(k) is the speed to apply now that the vehicle flies to waypoint k, None if nothing to do
    (no item before k, or already applied). reset() forgets what was applied (a new start).

    Scope: begin(current) remembers the planner's speed before the mission first changed it;
    observe(mission/status fields) returns, once the run is over, the speed to restore (and
    forgets it), else None. A run is over when another mission replaces it, or, after it was seen
    running (TAKEOFF / EXECUTING / HOLDING), when its last waypoint is reached or it lands or is
    IDLE; a start that fails ends it too (the caller restores)."""

    RUNNING = ("TAKEOFF", "EXECUTING", "HOLDING")

    def __init__(self, speeds: list[float | None] | None = None, mission_id: str = "",
                 restore: float | None = None):
        self.speeds = list(speeds or [])
        self.mission_id = mission_id
        self.applied: float | None = None
        self.restore = restore          # the planner's speed before this mission changed it
        self.running = False            # the run was seen under way since begin()

    def begin(self, current: float | None) -> None:
        if self.restore is None and current is not None:
            self.restore = float(current)
            self.running = False

    def end(self) -> float | None:
        """Forget the scope; the speed to restore (None if nothing was changed)."""
        speed, self.restore, self.running, self.applied = self.restore, None, False, None
        return speed

    def observe(self, mission_id: str, state: str, active_waypoint: int, total_waypoints: int) -> float | None:
        if self.restore is None:
            return None
        done = total_waypoints > 0 and active_waypoint >= total_waypoints
        if mission_id == self.mission_id and state in self.RUNNING and not done:
            self.running = True
            return None
        if mission_id != self.mission_id or (self.running and (done or state in ("IDLE", "LAND"))):
            return self.end()
        return None

    def reset(self) -> None:
        self.applied = None

    def due(self, k: int) -> float | None:
        if not 0 <= k < len(self.speeds):
            return None
        s = self.speeds[k]
        if s is None or s == self.applied:
            return None
        self.applied = s
        return s


def plan_id(items: list[Item]) -> int:
    """An opaque id of a plan (CRC-32 of every item's frame, command and values); 0 = no plan."""
    if not items:
        return 0
    crc = 0
    for it in items:
        crc = zlib.crc32(struct.pack("<HBHB7d", it.seq, it.frame & 0xFF, it.command & 0xFFFF, it.autocontinue & 0xFF,
                                     it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z), crc)
    return crc or 1


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
    (`mission_id`), from the stack's mission/status and mission/waypoint_reached (issue 9 #2):

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


def mission_to_items(mission: Mission, home: Home) -> list[Item]:
    """Mission -> items (NAV_TAKEOFF above home, NAV_WAYPOINT per waypoint, global-relative)."""
    items = [Item(seq=0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                  param4=math.nan, x=home.lat_deg, y=home.lon_deg,
                  z=mission.takeoff_altitude_m - home.local_m[2])]
    for wp in mission.waypoints:
        lat, lon, alt = home.to_geodetic(wp.x, wp.y, wp.z)
        yaw_ned = math.degrees(frames.yaw_enu_to_ned(math.radians(wp.yaw_deg)))
        items.append(Item(seq=len(items), frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                          command=M.MAV_CMD_NAV_WAYPOINT, param2=mission.waypoint_acceptance_radius_m,
                          param4=yaw_ned, x=lat, y=lon, z=alt))
    return items


# ---------------------------------------------------------------------------------------------
# Protocol


@dataclass
class Transfer:
    direction: str              # "upload" (GCS -> us) or "download" (us -> GCS)
    peer: tuple[int, int]       # (system, component) of the ground station
    count: int
    mission_type: int = 0
    items: list[Item | None] = field(default_factory=list)
    expected: int = 0
    last_send_s: float = 0.0
    retries: int = 0
    use_int: bool = True        # upload: MISSION_REQUEST_INT vs legacy MISSION_REQUEST


LoadFn = Callable[[list[Item], Callable[[bool, str, int], None]], None]


class MissionProtocol:
    """The mission micro-service (mission_type 0; fence/rally answered as empty).

    send(msg): transmit one MAVLink message object.
    load(items, done): hand a complete upload to the stack; done(ok, message, mav_result) may be
        called later (from another thread, under the same lock as the rest of the service).
    notify(text, peer): tell one ground station why its upload was refused (STATUSTEXT); by
        default the STATUSTEXT goes through send().

    One upload at a time: while one ground station uploads, another one's MISSION_COUNT,
    MISSION_REQUEST_LIST or MISSION_CLEAR_ALL is refused (MISSION_ACK DENIED, counted as "busy");
    the same ground station may restart its own upload.
    """

    def __init__(self, send: Callable, load: LoadFn, item_timeout_s: float = 0.25, retries: int = 5,
                 max_items: int = 500, log: Callable[..., None] | None = None,
                 notify: Callable[[str, tuple[int, int]], None] | None = None):
        self.send = send
        self.load = load
        self.notify = notify or (lambda text, peer: [self.send(m) for m in statustext(M.MAV_SEVERITY_CRITICAL, text)])
        self.item_timeout_s = item_timeout_s
        self.retries = retries
        self.max_items = max_items
        self.log = log or (lambda *a, **k: None)
        self.items = []                      # the accepted mission, as uploaded (sets plan_id)
        self.current = 0
        self.transfer: Transfer | None = None
        self.loading = False
        self.errors: dict[str, int] = {}
        self.uploads_accepted = 0
        self.uploads_rejected = 0

    @property
    def items(self) -> list[Item]:
        return self._items

    @items.setter
    def items(self, items: list[Item]) -> None:
        self._items = list(items)
        self.plan_id = plan_id(self._items)   # MISSION_CURRENT.mission_id, MISSION_ACK/COUNT opaque_id

    def _err(self, what: str) -> None:
        self.errors[what] = self.errors.get(what, 0) + 1

    def _ack(self, peer, result: int, mission_type: int = 0) -> None:
        opaque = self.plan_id if result == M.MAV_MISSION_ACCEPTED and mission_type == M.MAV_MISSION_TYPE_MISSION else 0
        self.send(MissionAck(peer[0], peer[1], result, mission_type, opaque))

    def _busy(self, peer, loading: bool = True) -> bool:
        """Another ground station's upload is under way (or, with `loading`, an upload is being
        loaded into the stack)."""
        t = self.transfer
        return (t is not None and t.direction == "upload" and t.peer != peer) or (loading and self.loading)

    # ------------------------------------------------------------ upload (GCS -> us)

    def on_count(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if self._busy(peer):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        if mtype != M.MAV_MISSION_TYPE_MISSION:
            # No fences or rally points here: an empty list is fine, anything else is unsupported.
            self._ack(peer, M.MAV_MISSION_ACCEPTED if msg.count == 0 else M.MAV_MISSION_UNSUPPORTED, mtype)
            return
        if msg.count > self.max_items:
            self._err("count_too_large")
            self.transfer = None
            self.notify(f"Mission rejected: {msg.count} items, at most {self.max_items}", peer)
            self._ack(peer, M.MAV_MISSION_NO_SPACE, mtype)
            return
        if msg.count == 0:
            self.transfer = None
            self.clear(peer)
            return
        self.transfer = Transfer("upload", peer, msg.count, mtype, [None] * msg.count, 0)
        self._request(now_s)

    def _request(self, now_s: float) -> None:
        t = self.transfer
        assert t is not None
        if t.use_int:
            self.send(M.MAVLink_mission_request_int_message(t.peer[0], t.peer[1], t.expected, t.mission_type))
        else:
            self.send(M.MAVLink_mission_request_message(t.peer[0], t.peer[1], t.expected, t.mission_type))
        t.last_send_s = now_s

    def on_item(self, msg, now_s: float) -> None:
        t = self.transfer
        if t is None or t.direction != "upload":
            self._err("item_without_upload")
            return
        if (msg.get_srcSystem(), msg.get_srcComponent()) != t.peer:
            self._err("item_from_other_peer")   # not part of the upload under way
            return
        if getattr(msg, "mission_type", 0) != t.mission_type:
            self._err("item_wrong_type")
            return
        if msg.seq != t.expected:
            # Out of order (or a duplicate): ask again for the one we need (seed §11: only the
            # expected seq is accepted).
            self._err("item_out_of_order")
            if msg.seq > t.expected:
                self._request(now_s)
            return
        if msg.get_type() == "MISSION_ITEM":
            t.use_int = False
        t.items[t.expected] = Item.from_msg(msg)
        t.expected += 1
        t.retries = 0
        if t.expected < t.count:
            self._request(now_s)
            return
        items = [it for it in t.items if it is not None]
        self.transfer = None
        self.loading = True
        peer, mtype = t.peer, t.mission_type

        def done(ok: bool, message: str, result: int = M.MAV_MISSION_ERROR) -> None:
            self.loading = False
            if ok:
                self.items = items
                self.current = 0
                self.uploads_accepted += 1
                self._ack(peer, M.MAV_MISSION_ACCEPTED, mtype)
            else:
                self.uploads_rejected += 1
                self.log("mission_rejected", message=message)
                self.notify(f"Mission rejected: {message}", peer)   # before the ACK: shown with it
                self._ack(peer, result if result != M.MAV_MISSION_ACCEPTED else M.MAV_MISSION_ERROR, mtype)

        self.load(items, done)

    # ------------------------------------------------------------ download (us -> GCS)

    def on_request_list(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype != M.MAV_MISSION_TYPE_MISSION:
            self.send(MissionCount(peer[0], peer[1], 0, mtype))
            return
        if self._busy(peer, loading=False):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        n = len(self.items)
        self.send(MissionCount(peer[0], peer[1], n, mtype, self.plan_id))
        self.transfer = Transfer("download", peer, n, mtype, list(self.items), 0, now_s) if n else None

    def on_request(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype != M.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self.items):
            self._err("request_out_of_range")
            self._ack(peer, M.MAV_MISSION_INVALID_SEQUENCE, mtype)
            return
        it = self.items[msg.seq]
        it.current = 1 if msg.seq == self.current else 0
        if msg.get_type() == "MISSION_REQUEST_INT":
            self.send(it.to_msg_int(peer[0], peer[1], mtype))
        else:
            self.send(it.to_msg_legacy(peer[0], peer[1], mtype))
        if self.transfer is not None and self.transfer.direction == "download":
            self.transfer.last_send_s = now_s

    def on_ack(self, msg, now_s: float) -> None:
        if self.transfer is not None and (msg.get_srcSystem(), msg.get_srcComponent()) != self.transfer.peer:
            return   # another ground station's ACK says nothing about this transfer
        if self.transfer is not None and self.transfer.direction == "download":
            self.transfer = None
        elif self.transfer is not None and self.transfer.direction == "upload" and msg.type != M.MAV_MISSION_ACCEPTED:
            self.transfer = None  # the ground station cancelled its upload

    # ------------------------------------------------------------ clear / current

    def clear(self, peer, mission_type: int = 0) -> None:
        self.items = []
        self.current = 0
        self._ack(peer, M.MAV_MISSION_ACCEPTED, mission_type)

    def on_clear_all(self, msg, now_s: float) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = getattr(msg, "mission_type", 0)
        if mtype not in (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_ALL):
            self._ack(peer, M.MAV_MISSION_ACCEPTED, mtype)
            return
        if self._busy(peer):
            self._err("busy")
            self._ack(peer, M.MAV_MISSION_DENIED, mtype)
            return
        self.transfer = None
        self.clear(peer, mtype)

    def set_current(self, seq: int) -> bool:
        if not 0 <= seq < len(self.items):
            self._err("set_current_out_of_range")
            return False
        self.current = seq
        return True

    # ------------------------------------------------------------ timers

    def tick(self, now_s: float) -> None:
        t = self.transfer
        if t is None:
            return
        if t.direction == "upload":
            if now_s - t.last_send_s < self.item_timeout_s:
                return
            if t.retries >= self.retries:
                self._err("upload_timeout")
                self.transfer = None
                self._ack(t.peer, M.MAV_MISSION_OPERATION_CANCELLED, t.mission_type)
                return
            t.retries += 1
            self._request(now_s)
        elif now_s - t.last_send_s > max(5.0, self.item_timeout_s * self.retries * 4):
            self.transfer = None  # the ground station stopped asking; forget the download

    def handle(self, msg, now_s: float) -> bool:
        """Dispatch one mission-protocol message; False if it is not one."""
        fn = {
            "MISSION_COUNT": self.on_count, "MISSION_ITEM_INT": self.on_item, "MISSION_ITEM": self.on_item,
            "MISSION_REQUEST_LIST": self.on_request_list, "MISSION_REQUEST_INT": self.on_request,
            "MISSION_REQUEST": self.on_request, "MISSION_ACK": self.on_ack,
            "MISSION_CLEAR_ALL": self.on_clear_all,
        }.get(msg.get_type())
        if fn is None:
            return False
        fn(msg, now_s)
        return True
