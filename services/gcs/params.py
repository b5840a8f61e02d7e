"""The stack's live parameters as one MAVLink parameter table (no Zenoh).

Every exposed service's declared parameters (config/<service>/@params) get a MAVLink name of at
most 16 characters: a 3-letter service prefix, then the parameter name upper-cased without its
unit suffix, shortened word by word when too long (planner.max_velocity_mps -> PLN_MAX_VELOCITY,
mission.takeoff_altitude_m -> MIS_TAKEO_ALTITU). Names are stable for a given declaration, and
unique (a clash gets a numeric suffix). Floats are REAL32; ints and bools are INT32 / UINT8 sent
byte-wise (PARAM_ENCODE_BYTEWISE, as PX4 does); string parameters have no MAVLink form and are
not exposed.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any, Iterable

from pymavlink.dialects.v20 import common as M

PREFIXES = {"planner": "PLN", "mission": "MIS", "fmu": "FMU", "gcs": "GCS", "safety": "SAF",
            "vio": "VIO", "detector": "DET", "lidar": "LID", "perception": "PRC", "sim": "SIM",
            "diagnostics": "DIA", "recorder": "REC", "viz": "VIZ"}
UNIT_SUFFIXES = ("_mps2", "_mps", "_radps", "_rad", "_deg", "_hz", "_m", "_s", "_ms", "_v", "_a")
MAX_LEN = 16


def prefix_for(service: str) -> str:
    return PREFIXES.get(service, service[:3].upper())


def mavlink_name(service: str, name: str) -> str:
    """Deterministic 16-character MAVLink name for service.name (before clash resolution)."""
    base = name.lower()
    for suf in UNIT_SUFFIXES:
        if base.endswith(suf) and len(base) > len(suf):
            base = base[: -len(suf)]
            break
    words = [prefix_for(service)] + [w.upper() for w in base.split("_") if w]
    while len("_".join(words)) > MAX_LEN:
        i = max(range(1, len(words)), key=lambda k: len(words[k]), default=None)
        if i is None or len(words[i]) <= 1:
            break
        if len(words[i]) <= 3 and len(words) > 2:
            words.pop(i)  # every word already short: drop one
            continue
        words[i] = words[i][:-1]
    return "_".join(words)[:MAX_LEN]


@dataclass
class Entry:
    service: str
    name: str            # the service's own parameter name
    mav_name: str
    value: Any
    ptype: int           # MAV_PARAM_TYPE
    min: float | None = None
    max: float | None = None
    default: Any = None


def param_type_of(value: Any, declared: str = "") -> int | None:
    t = declared or type(value).__name__
    if t == "bool":
        return M.MAV_PARAM_TYPE_UINT8
    if t == "int":
        return M.MAV_PARAM_TYPE_INT32
    if t == "float":
        return M.MAV_PARAM_TYPE_REAL32
    return None


def encode_value(value: Any, ptype: int) -> float:
    """Our value -> PARAM_VALUE.param_value (byte-wise for integer types)."""
    if ptype == M.MAV_PARAM_TYPE_REAL32:
        return float(value)
    if ptype == M.MAV_PARAM_TYPE_UINT8:
        raw = struct.pack("<I", 1 if value else 0)
    else:
        raw = struct.pack("<i", int(value))
    return struct.unpack("<f", raw)[0]


def decode_value(param_value: float, ptype: int, declared_type: int) -> Any:
    """PARAM_SET.param_value -> our value. Integer types arrive byte-wise; a ground station that
    sends an integer as a plain float (cast) is accepted too when the bytes are implausible."""
    if declared_type == M.MAV_PARAM_TYPE_REAL32:
        if ptype in (M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_UINT8, M.MAV_PARAM_TYPE_UINT32):
            return float(_bytewise_int(param_value, ptype))
        return shortest_float32(param_value)
    as_int = _bytewise_int(param_value, ptype if ptype != M.MAV_PARAM_TYPE_REAL32 else M.MAV_PARAM_TYPE_INT32)
    if ptype == M.MAV_PARAM_TYPE_REAL32 and math.isfinite(param_value) and float(param_value).is_integer():
        as_int = int(param_value)  # cast encoding (e.g. MAVProxy): 1.0 means 1
    if declared_type == M.MAV_PARAM_TYPE_UINT8:
        return bool(as_int)
    return as_int


def shortest_float32(value: float) -> float:
    """The shortest decimal that is the same float32: a ground station's 1.1 arrives as the float32
    1.100000023841858; the service should get 1.1, what the operator typed."""
    value = float(value)
    if not math.isfinite(value):
        return value
    f32 = struct.unpack("<f", struct.pack("<f", value))[0]
    for digits in range(6, 10):
        candidate = float(f"{f32:.{digits}g}")
        if struct.unpack("<f", struct.pack("<f", candidate))[0] == f32:
            return candidate
    return f32


def _bytewise_int(param_value: float, ptype: int) -> int:
    raw = struct.pack("<f", param_value)
    if ptype == M.MAV_PARAM_TYPE_UINT8:
        return raw[0]
    if ptype in (M.MAV_PARAM_TYPE_UINT32,):
        return struct.unpack("<I", raw)[0]
    return struct.unpack("<i", raw)[0]


def decode_param_id(param_id: Any) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return str(param_id).split("\x00", 1)[0].strip()


class ParamTable:
    """Ordered table of exposed parameters; index = position (stable per set of services)."""

    def __init__(self, services: Iterable[str]):
        self.services = [s for s in services if s]
        self.by_service: dict[str, list[Entry]] = {}
        self.entries: list[Entry] = []
        self.by_mav: dict[str, Entry] = {}

    def update_service(self, service: str, descriptors: Iterable[Any]) -> bool:
        """Replace one service's entries from its ParamDescriptor list; True if the table changed."""
        out = []
        for d in descriptors:
            pt = param_type_of(d.value, d.type)
            if pt is None:
                continue
            out.append(Entry(service, d.name, "", d.value, pt, d.min, d.max, d.default))
        old = [(e.name, e.value) for e in self.by_service.get(service, [])]
        self.by_service[service] = out
        self._rebuild()
        return old != [(e.name, e.value) for e in out]

    def _rebuild(self) -> None:
        self.entries, self.by_mav = [], {}
        for s in self.services:
            for e in self.by_service.get(s, []):
                name = mavlink_name(s, e.name)
                n = 2
                while name in self.by_mav:
                    suffix = str(n)
                    name = name[: MAX_LEN - len(suffix)] + suffix
                    n += 1
                e.mav_name = name
                self.entries.append(e)
                self.by_mav[name] = e

    def __len__(self) -> int:
        return len(self.entries)

    def find(self, service: str, name: str) -> tuple[int, Entry] | None:
        """A service's parameter by its own name (not the MAVLink one)."""
        for i, e in enumerate(self.entries):
            if e.service == service and e.name == name:
                return i, e
        return None

    def lookup(self, name: str | None = None, index: int = -1) -> tuple[int, Entry] | None:
        """PARAM_REQUEST_READ semantics: index >= 0 wins, else the name."""
        if index is not None and index >= 0:
            return (index, self.entries[index]) if index < len(self.entries) else None
        e = self.by_mav.get(name or "")
        return (self.entries.index(e), e) if e is not None else None

    def value_msg(self, index: int, entry: Entry):
        return M.MAVLink_param_value_message(entry.mav_name.encode(), encode_value(entry.value, entry.ptype),
                                             entry.ptype, len(self.entries), index)
