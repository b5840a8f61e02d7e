"""MAVLink mission items <-> the stack's Mission (ENU about home), without Zenoh.

Geodetic <-> local ENU goes through home.Home (PX4's projection, services/lib/geo.py), and
every NED<->ENU step through services/mavlink/frames.py.
Accepted items: NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, NAV_RETURN_TO_LAUNCH, DO_CHANGE_SPEED in
frames GLOBAL[_INT] (AMSL), GLOBAL_RELATIVE_ALT[_INT], LOCAL_NED, LOCAL_ENU. A takeoff item sets
the mission's takeoff altitude; LAND adds its position (when it has one) and ends the mission;
RTL flies back above home. Yaw (param4, NED heading deg, NaN = keep) becomes ENU yaw_deg.
DO_CHANGE_SPEED items are checked here but are not part of the Mission (see mission_speed.py).
A waypoint at or below home altitude is refused (MAV_MISSION_INVALID_PARAM7, naming the item), in
every frame alike: global-relative z <= 0, AMSL z <= home's altitude (an AMSL item at home
altitude would otherwise become a waypoint at ground level), local z at or below home's;
NAV_LAND and RTL items are exempt. (The mission service's geofence floor applies on top.)

Plan id. `plan_id(items)` is a CRC-32 of the items (never 0: 0 means "no mission"); gcs reports
it as MISSION_CURRENT.mission_id and in MISSION_ACK / MISSION_COUNT opaque_id (MAVLink extension
fields, see messages.py), so a ground station notices that the mission on the vehicle changed.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import Mission, Waypoint
from aeroperception.services.mavlink import frames

from .home import Home
from .mission_speed import change_speed_value

GLOBAL_FRAMES = {M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT}
RELATIVE_FRAMES = {M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
LOCAL_FRAMES = {M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_ENU}
NAV_POSITION = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND}
SUPPORTED_COMMANDS = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND,
                      M.MAV_CMD_NAV_RETURN_TO_LAUNCH, M.MAV_CMD_DO_CHANGE_SPEED}


class MissionConversionError(ValueError):
    """An item we cannot fly, with the MAV_MISSION_RESULT to answer and a readable reason."""

    def __init__(self, result: int, message: str):
        super().__init__(message)
        self.result = result


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


def plan_id(items: list[Item]) -> int:
    """An opaque id of a plan (CRC-32 of every item's frame, command and values); 0 = no plan."""
    if not items:
        return 0
    crc = 0
    for it in items:
        crc = zlib.crc32(struct.pack("<HBHB7d", it.seq, it.frame & 0xFF, it.command & 0xFFFF, it.autocontinue & 0xFF,
                                     it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z), crc)
    return crc or 1
