"""Parameter values on the wire: PARAM_VALUE and PARAM_SET carry every value in one float field.
Integers travel byte-wise (PARAM_ENCODE_BYTEWISE, as PX4 sends them): the integer's four bytes
read as a float32, not the integer converted to a float.
"""
from __future__ import annotations

import struct
from typing import Any

from pymavlink.dialects.v20 import common as M


def int_to_float_bits(value: int) -> float:
    """An int32's four bytes as the float32 that carries them."""
    return struct.unpack("<f", struct.pack("<i", value))[0]


def float_bits_to_int(wire: float, ptype: int = M.MAV_PARAM_TYPE_INT32) -> int:
    """The integer a byte-wise float carries: UINT8 its first byte, UINT32 unsigned, else int32."""
    raw = struct.pack("<f", wire)
    if ptype == M.MAV_PARAM_TYPE_UINT8:
        return raw[0]
    if ptype == M.MAV_PARAM_TYPE_UINT32:
        return struct.unpack("<I", raw)[0]
    return struct.unpack("<i", raw)[0]


def encode_value(value: Any, ptype: int) -> float:
    """A value -> the float field carrying it as `ptype` (MAV_PARAM_TYPE): REAL32 as it is,
    integer types (bool as UINT8 0/1) byte-wise."""
    if ptype == M.MAV_PARAM_TYPE_REAL32:
        return float(value)
    if ptype == M.MAV_PARAM_TYPE_UINT8:
        return int_to_float_bits(1 if value else 0)
    return int_to_float_bits(int(value))
