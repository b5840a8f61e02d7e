"""MAVLink messages pymavlink's `common` (2.4.x) builds without fields the current MAVLink spec
has, and STATUSTEXT chunking.

MAVLink 2 extension fields are appended to the payload after the existing ones and do not change
CRC_EXTRA, so a receiver that knows fewer fields simply ignores the extra bytes (pymavlink
truncates them) and one that knows more reads them:

- MISSION_CURRENT: + mission_id, fence_id, rally_points_id (uint32 each);
- MISSION_COUNT, MISSION_ACK: + opaque_id (uint32): the plan's id, the same as MISSION_CURRENT's
  mission_id for the mission.

`extension_fields(msg)` reads them back from a received message (any pymavlink object).
"""
from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as M

STATUSTEXT_LEN = 50


class MissionCurrent(M.MAVLink_mission_current_message):
    fieldnames = ["seq", "total", "mission_state", "mission_mode", "mission_id", "fence_id", "rally_points_id"]
    ordered_fieldnames = fieldnames
    fieldtypes = ["uint16_t", "uint16_t", "uint8_t", "uint8_t", "uint32_t", "uint32_t", "uint32_t"]
    orders = [0, 1, 2, 3, 4, 5, 6]
    lengths = [1] * 7
    array_lengths = [0] * 7
    unpacker = struct.Struct("<HHBBIII")

    def __init__(self, seq: int, total: int = 0, mission_state: int = 0, mission_mode: int = 0,
                 mission_id: int = 0, fence_id: int = 0, rally_points_id: int = 0):
        super().__init__(seq, total, mission_state, mission_mode)
        self._fieldnames = MissionCurrent.fieldnames
        self.mission_id, self.fence_id, self.rally_points_id = mission_id, fence_id, rally_points_id

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        return self._pack(mav, self.crc_extra, self.unpacker.pack(
            self.seq, self.total, self.mission_state, self.mission_mode, self.mission_id, self.fence_id,
            self.rally_points_id), force_mavlink1=force_mavlink1)


class MissionCount(M.MAVLink_mission_count_message):
    fieldnames = ["target_system", "target_component", "count", "mission_type", "opaque_id"]
    ordered_fieldnames = ["count", "target_system", "target_component", "mission_type", "opaque_id"]
    fieldtypes = ["uint8_t", "uint8_t", "uint16_t", "uint8_t", "uint32_t"]
    orders = [1, 2, 0, 3, 4]
    lengths = [1] * 5
    array_lengths = [0] * 5
    unpacker = struct.Struct("<HBBBI")

    def __init__(self, target_system: int, target_component: int, count: int, mission_type: int = 0,
                 opaque_id: int = 0):
        super().__init__(target_system, target_component, count, mission_type)
        self._fieldnames = MissionCount.fieldnames
        self.opaque_id = opaque_id

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        return self._pack(mav, self.crc_extra, self.unpacker.pack(
            self.count, self.target_system, self.target_component, self.mission_type, self.opaque_id),
            force_mavlink1=force_mavlink1)


class MissionAck(M.MAVLink_mission_ack_message):
    fieldnames = ["target_system", "target_component", "type", "mission_type", "opaque_id"]
    ordered_fieldnames = fieldnames
    fieldtypes = ["uint8_t", "uint8_t", "uint8_t", "uint8_t", "uint32_t"]
    orders = [0, 1, 2, 3, 4]
    lengths = [1] * 5
    array_lengths = [0] * 5
    unpacker = struct.Struct("<BBBBI")

    def __init__(self, target_system: int, target_component: int, type: int, mission_type: int = 0,  # noqa: A002
                 opaque_id: int = 0):
        super().__init__(target_system, target_component, type, mission_type)
        self._fieldnames = MissionAck.fieldnames
        self.opaque_id = opaque_id

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        return self._pack(mav, self.crc_extra, self.unpacker.pack(
            self.target_system, self.target_component, self.type, self.mission_type, self.opaque_id),
            force_mavlink1=force_mavlink1)


_EXTENDED = {M.MAVLINK_MSG_ID_MISSION_CURRENT: MissionCurrent, M.MAVLINK_MSG_ID_MISSION_COUNT: MissionCount,
             M.MAVLINK_MSG_ID_MISSION_ACK: MissionAck}


def extension_fields(msg) -> dict[str, int]:
    """The fields of a received MISSION_CURRENT / MISSION_COUNT / MISSION_ACK as the current spec
    has them (missing trailing bytes are zeros), read from the raw frame."""
    cls = _EXTENDED.get(msg.get_msgId())
    if cls is None:
        return {}
    buf = bytes(msg.get_msgbuf())
    if buf[0] == M.PROTOCOL_MARKER_V2:
        payload = buf[10:10 + buf[1]]
    else:
        payload = buf[6:6 + buf[1]]
    payload = payload[:cls.unpacker.size].ljust(cls.unpacker.size, b"\0")
    return dict(zip(cls.ordered_fieldnames, cls.unpacker.unpack(payload)))


def statustext(severity: int, text: str, chunk_id: int = 0) -> list:
    """STATUSTEXT message(s): one if the text fits in 50 characters, else chunks sharing a
    nonzero id (chunk_seq 0, 1, ...), the last one shorter than 50 (an empty one if needed)."""
    data = text.encode("utf-8", "replace")
    if len(data) <= STATUSTEXT_LEN:
        return [M.MAVLink_statustext_message(severity, data, 0, 0)]
    chunk_id = (chunk_id & 0xFFFF) or 1
    out = []
    for seq, i in enumerate(range(0, len(data) + 1, STATUSTEXT_LEN)):
        out.append(M.MAVLink_statustext_message(severity, data[i:i + STATUSTEXT_LEN], chunk_id, seq))
        if len(data) - i < STATUSTEXT_LEN:
            break
    return out
