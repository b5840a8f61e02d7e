"""The home gcs converts about (no Zenoh): the flight controller's, once fmu reports it on
fmu/out/home_position, else the home_* parameters (seed 001 §15's default) with home at the local
origin.

Every geodetic <-> local conversion of gcs (GLOBAL_POSITION_INT, GPS_RAW_INT, HOME_POSITION,
mission items, DO_REPOSITION / NAV_TAKEOFF altitudes) uses `HomeTracker.home`. A new home that
arrives while a mission upload is under way (items being received, or the upload being loaded
into the stack) is held back and applied once the upload is over, so one upload is converted
about one home.
"""
from __future__ import annotations

import math
from typing import Callable

from aeroperception.schemas import HomePosition

from .missions import Home

SOURCE_PARAM = "param"
SOURCE_FC = "flight_controller"


def home_from_msg(msg: HomePosition) -> Home | None:
    """HomePosition (fmu/out/home_position) -> Home; None if it is not a usable home."""
    vals = (msg.latitude_deg, msg.longitude_deg, msg.altitude_amsl_m,
            msg.position_m.x, msg.position_m.y, msg.position_m.z)
    if not all(math.isfinite(v) for v in vals) or not (-90.0 <= msg.latitude_deg <= 90.0) \
            or not (-180.0 <= msg.longitude_deg <= 180.0):
        return None
    return Home(float(msg.latitude_deg), float(msg.longitude_deg), float(msg.altitude_amsl_m),
                (float(msg.position_m.x), float(msg.position_m.y), float(msg.position_m.z)))


def origin_shift_m(old: Home, new: Home) -> float:
    """How far (horizontally, metres) the same local position moves on the Earth from `old` to `new`."""
    north, east = new.origin.project(old.origin.lat_deg, old.origin.lon_deg)
    return math.hypot(north, east)


class HomeTracker:
    """The home in force and where it came from (`source`: "param" or "flight_controller").

    busy(): whether a mission upload is under way (a change is then held in `pending`).
    apply(new, old, source): called whenever the home in force changes (not for a repeat).
    """

    def __init__(self, fallback: Home, busy: Callable[[], bool],
                 apply: Callable[[Home, Home, str], None] | None = None):
        self.fallback = fallback
        self.home = fallback
        self.source = SOURCE_PARAM
        self.pending: Home | None = None
        self.busy = busy
        self.apply = apply or (lambda new, old, source: None)
        self.changes = 0

    def offer(self, home: Home) -> bool:
        """A home from the flight controller (repeated at 1 Hz). True if it is now in force and
        differs from the one before; False for a repeat or when held back (see `pending`)."""
        if self.source == SOURCE_FC and home == self.home:
            self.pending = None          # back to the home in force: nothing held any more
            return False
        if self.busy():
            self.pending = home
            return False
        self.pending = None
        old, self.home, self.source = self.home, home, SOURCE_FC
        self.changes += 1
        self.apply(home, old, SOURCE_FC)
        return True

    def poll(self) -> bool:
        """Apply a held-back home once no upload is under way (call periodically)."""
        if self.pending is None or self.busy():
            return False
        return self.offer(self.pending)
