"""Home (where the local ENU frame sits on the Earth) and the home gcs converts about, without
Zenoh: the flight controller's, once fmu reports it on fmu/out/home_position, else the home_*
parameters with home at the local origin.

Every geodetic <-> local conversion of gcs (GLOBAL_POSITION_INT, GPS_RAW_INT, HOME_POSITION,
mission items, DO_REPOSITION / NAV_TAKEOFF altitudes) uses `HomeTracker.home`. A new home that
arrives while a mission upload is under way (items being received, or the upload being loaded
into the stack) is held back and applied once the upload is over, so one upload is converted
about one home.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Callable

from aeroperception.schemas import HomePosition
from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.mavlink import frames

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


def mission_needs_upload_again(old: Home, new: Home) -> bool:
    """A home that moved (horizontally or in the altitude of its local origin) by more than 0.5 m:
    a mission loaded about the old one was converted about the wrong place."""
    return (origin_shift_m(old, new) > 0.5
            or abs(new.alt_m - new.local_m[2] - old.alt_m + old.local_m[2]) > 0.5)
