"""The stack's live parameters as one MAVLink parameter table (no Zenoh).

Every exposed service's declared parameters (config/<service>/@params) get a MAVLink name of at
most 16 characters: a 3-letter service prefix, then the parameter name upper-cased without its
unit suffix, shortened word by word when too long (planner.max_velocity_mps -> PLN_MAX_VELOCITY,
mission.takeoff_altitude_m -> MIS_TAKEO_ALTITU). Names are stable for a given declaration, and
unique (a clash gets a numeric suffix). Floats are REAL32; ints and bools are INT32 / UINT8 sent
byte-wise (PARAM_ENCODE_BYTEWISE, as PX4 does); string parameters have no MAVLink form and are
not exposed.

PX4 names. Ground stations and scripts use PX4's well-known names, so where the
stack has the setting it is also served under PX4's name (`ALIASES`), mapped to the owning
services' live parameters: a read shows the service's value, a PARAM_SET goes to every owning
service's config/<svc>/@set (GF_MAX_HOR_DIST / GF_MAX_VER_DIST to both mission and safety, which
share services/lib/geofence.py's GEOFENCE_PARAMS) and the reply is the value in force. An
alias exists only while one of its services has answered @params (safety or the simulator not
running -> the name is absent, as on a PX4 without that module). A few settings ground stations
read on connect have no parameter in the stack but a fixed, true answer (`Alias.constant`, read
only: a set is refused with a STATUSTEXT and the value echoed).

Unknown names, as PX4 answers them: PARAM_REQUEST_READ by name -> no PARAM_VALUE; PARAM_SET ->
STATUSTEXT "[pm] unknown param: NAME" and no PARAM_VALUE. Beside that, gcs sends MAVLink 2's
PARAM_ERROR (DOES_NOT_EXIST / READ_ONLY), which ground stations that know it (QGC) show at once
and others ignore.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any, Iterable

from pymavlink.dialects.v20 import common as M

from aeroperception.services.mavlink.param_value import encode_value, float_bits_to_int

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
    targets: tuple[tuple[str, str], ...] = ()   # a PX4-named alias: the (service, name) it reads and sets
    readonly: str = ""                          # why it cannot be set ("" = settable)


ALIAS_SERVICE = "px4"   # Entry.service of a PX4-named alias


@dataclass(frozen=True)
class Alias:
    """A PX4 parameter name served for the stack's own setting(s)."""

    name: str
    ptype: int
    targets: tuple[tuple[str, str], ...] = ()   # read from the first present, set on all present
    constant: Any = None                        # no parameter in the stack: this fixed, true value
    why: str = ""                               # what the value means for the stack (docs, read-only reason)


_F, _I = M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT32
ALIASES: tuple[Alias, ...] = (
    Alias("MIS_TAKEOFF_ALT", _F, (("mission", "takeoff_altitude_m"),)),
    Alias("MPC_XY_VEL_MAX", _F, (("planner", "max_velocity_mps"),)),
    Alias("NAV_ACC_RAD", _F, (("planner", "acceptance_radius_m"), ("mission", "acceptance_radius_m")),
          why="also the acceptance radius of uploaded items without one (param2 0), as in PX4"),
    Alias("GF_MAX_HOR_DIST", _F, (("mission", "geofence_radius_m"), ("safety", "geofence_radius_m"))),
    Alias("GF_MAX_VER_DIST", _F, (("mission", "geofence_max_altitude_m"), ("safety", "geofence_max_altitude_m"))),
    Alias("GF_ACTION", _I, (("safety", "geofence_action"),),
          why="PX4 enum: 0 none, 1 warning, 2 hold, 3 return, 4 terminate (refused by safety), 5 land"),
    Alias("RTL_RETURN_ALT", _F, (("sim", "RTL_RETURN_ALT"),),
          why="the simulated flight controller's; with a real FC it is the FC's own parameter (absent here)"),
    Alias("COM_RC_IN_MODE", _I, constant=4,
          why="4 = stick input disabled: MANUAL_CONTROL is republished on gcs/joystick, nothing flies with it"),
    Alias("NAV_DLL_ACT", _I, constant=1,
          why="1 = hold: the mission service holds when gcs/link goes from up to down"),
)


def param_type_of(value: Any, declared: str = "") -> int | None:
    t = declared or type(value).__name__
    if t == "bool":
        return M.MAV_PARAM_TYPE_UINT8
    if t == "int":
        return M.MAV_PARAM_TYPE_INT32
    if t == "float":
        return M.MAV_PARAM_TYPE_REAL32
    return None


def decode_value(param_value: float, ptype: int, declared_type: int) -> Any:
    """PARAM_SET.param_value -> our value. Integer types arrive byte-wise; a ground station that
    sends an integer as a plain float (cast) is accepted too when the bytes are implausible."""
    if declared_type == M.MAV_PARAM_TYPE_REAL32:
        if ptype in (M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_UINT8, M.MAV_PARAM_TYPE_UINT32):
            return float(float_bits_to_int(param_value, ptype))
        return shortest_float32(param_value)
    as_int = float_bits_to_int(param_value, ptype if ptype != M.MAV_PARAM_TYPE_REAL32 else M.MAV_PARAM_TYPE_INT32)
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


def decode_param_id(param_id: Any) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return str(param_id).split("\x00", 1)[0].strip()


class ParamTable:
    """Ordered table of exposed parameters; index = position (stable per set of services): each
    exposed service's parameters under gcs's names, then the PX4-named aliases present."""

    def __init__(self, services: Iterable[str], aliases: Iterable[Alias] = ALIASES):
        self.services = [s for s in services if s]
        self.aliases = tuple(aliases)
        self.by_service: dict[str, list[Entry]] = {}
        self.entries: list[Entry] = []
        self.by_mav: dict[str, Entry] = {}
        self._rebuild()

    @property
    def sources(self) -> list[str]:
        """Every service whose @params we read: the exposed ones and the aliases' owners."""
        out = list(self.services)
        for a in self.aliases:
            out += [svc for svc, _ in a.targets if svc not in out]
        return out

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
        aliases = [e for e in (self._alias_entry(a) for a in self.aliases) if e is not None]
        reserved = {e.mav_name for e in aliases}
        for s in self.services:
            for e in self.by_service.get(s, []):
                name = mavlink_name(s, e.name)
                n = 2
                while name in self.by_mav or name in reserved:
                    suffix = str(n)
                    name = name[: MAX_LEN - len(suffix)] + suffix
                    n += 1
                e.mav_name = name
                self.entries.append(e)
                self.by_mav[name] = e
        for e in aliases:
            self.entries.append(e)
            self.by_mav[e.mav_name] = e

    def _native(self, service: str, name: str) -> Entry | None:
        for e in self.by_service.get(service, []):
            if e.name == name:
                return e
        return None

    def _alias_entry(self, a: Alias) -> Entry | None:
        if a.constant is not None:
            return Entry(ALIAS_SERVICE, a.name, a.name, a.constant, a.ptype, a.constant, a.constant, a.constant,
                         readonly=a.why)
        present = [(svc, n, e) for svc, n in a.targets if (e := self._native(svc, n)) is not None]
        if not present:
            return None
        first = present[0][2]
        lows = [e.min for _, _, e in present if e.min is not None]
        highs = [e.max for _, _, e in present if e.max is not None]
        value = first.value if a.ptype != M.MAV_PARAM_TYPE_INT32 else int(first.value)
        return Entry(ALIAS_SERVICE, a.name, a.name, value, a.ptype, max(lows) if lows else None,
                     min(highs) if highs else None, first.default, tuple((svc, n) for svc, n, _ in present))

    def set_value(self, service: str, name: str, value: Any) -> None:
        """A value a service confirmed (its @set reply): the native entry and every alias of it."""
        e = self._native(service, name)
        if e is not None and e.value != value:
            e.value = value
            self._rebuild()

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
