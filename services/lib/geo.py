"""Local NED <-> WGS84 around a reference point, as PX4's MapProjection (lib/geo) does it.

Azimuthal equidistant projection on a sphere of PX4's Earth radius, so a GLOBAL_POSITION_INT
we compute from a local position matches what PX4 would report for the same state (and the
inverse recovers the local position to millimetres over the few kilometres a mission spans).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6371000.0  # CONSTANTS_RADIUS_OF_EARTH in PX4


@dataclass(frozen=True)
class MapProjection:
    """Reference (origin of the local frame) in degrees; altitude is kept by the caller."""

    lat_deg: float
    lon_deg: float

    def project(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """WGS84 -> local (north_m, east_m)."""
        ref_lat, ref_lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        cos_d_lon = math.cos(lon - ref_lon)
        arg = max(-1.0, min(1.0, math.sin(ref_lat) * math.sin(lat)
                            + math.cos(ref_lat) * math.cos(lat) * cos_d_lon))
        c = math.acos(arg)
        k = 1.0 if abs(c) < 1e-12 else c / math.sin(c)
        north = k * (math.cos(ref_lat) * math.sin(lat) - math.sin(ref_lat) * math.cos(lat) * cos_d_lon)
        east = k * math.cos(lat) * math.sin(lon - ref_lon)
        return north * EARTH_RADIUS_M, east * EARTH_RADIUS_M

    def reproject(self, north_m: float, east_m: float) -> tuple[float, float]:
        """Local (north_m, east_m) -> WGS84 (lat_deg, lon_deg)."""
        ref_lat, ref_lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        x, y = north_m / EARTH_RADIUS_M, east_m / EARTH_RADIUS_M
        c = math.hypot(x, y)
        if c < 1e-15:
            return self.lat_deg, self.lon_deg
        sin_c, cos_c = math.sin(c), math.cos(c)
        lat = math.asin(cos_c * math.sin(ref_lat) + x * sin_c * math.cos(ref_lat) / c)
        lon = ref_lon + math.atan2(y * sin_c, c * math.cos(ref_lat) * cos_c - x * math.sin(ref_lat) * sin_c)
        return math.degrees(lat), math.degrees(lon)
