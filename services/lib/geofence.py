"""The geofence: one definition used by the safety service (live distance to the boundary) and
by the mission service (waypoints checked before a mission is accepted).

A vertical cylinder about the local origin (the flight controller's home, ENU) with a ceiling,
a floor for commanded positions, and an optional keep-in polygon (ENU x/y vertices, metres).
PX4's names for the same settings: GF_MAX_HOR_DIST (radius), GF_MAX_VER_DIST (ceiling),
GF_ACTION (what to do on a breach; safety's `geofence_action`).
Both services declare GEOFENCE_PARAMS so a ground station can set one value on both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from aeroperception.services.runtime import Param
from aeroperception.services.runtime.config import build, param

GEOFENCE_PARAMS = [
    Param("geofence_radius_m", 500.0, "m", 1.0, 100_000.0,
          description="max horizontal distance from home (PX4 GF_MAX_HOR_DIST)"),
    Param("geofence_max_altitude_m", 120.0, "m", 1.0, 10_000.0,
          description="max altitude above home (PX4 GF_MAX_VER_DIST)"),
    Param("geofence_min_altitude_m", 0.5, "m", 0.0, 100.0,
          description="lowest commanded waypoint altitude above home (no waypoint into the ground)"),
    Param("geofence_polygon", "", description="optional keep-in polygon 'x1,y1;x2,y2;...' (m, ENU about home)"),
]


class GeofenceError(ValueError):
    """A geofence setting that does not parse (e.g. a polygon with fewer than 3 vertices)."""


@dataclass(frozen=True)
class Geofence:
    """The GEOFENCE_PARAMS (a config section: runtime/config.py builds it, defaults declared once,
    above; a polygon that does not parse raises GeofenceError, refusing the value)."""

    radius_m: float = param("geofence_radius_m")
    max_altitude_m: float = param("geofence_max_altitude_m")
    min_altitude_m: float = param("geofence_min_altitude_m")
    polygon: tuple[tuple[float, float], ...] = param("geofence_polygon", lambda text: parse_polygon(text))

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | Iterable[Param] = GEOFENCE_PARAMS, **overrides: Any) -> "Geofence":
        """The fence from parameter values (default: the declared defaults); `overrides` by field name."""
        return build(cls, params, **overrides)

    def distance_to_boundary_m(self, x: float, y: float, z: float) -> float:
        """Signed distance to the nearest boundary: > 0 inside, < 0 outside (ceiling and
        cylinder wall; the floor is a limit for commanded positions only, not for flight)."""
        d = min(self.radius_m - math.hypot(x, y), self.max_altitude_m - z)
        if self.polygon:
            d = min(d, _polygon_signed_distance(self.polygon, x, y))
        return d

    def check_waypoint(self, x: float, y: float, z: float) -> str | None:
        """Why a commanded position is outside the fence, or None if it is allowed."""
        if not all(math.isfinite(v) for v in (x, y, z)):
            return "position is not finite"
        if z < self.min_altitude_m:
            return f"altitude {z:.2f} m is below the geofence floor {self.min_altitude_m:.2f} m"
        if z > self.max_altitude_m:
            return f"altitude {z:.1f} m is above the geofence ceiling {self.max_altitude_m:.1f} m"
        r = math.hypot(x, y)
        if r > self.radius_m:
            return f"{r:.1f} m from home is outside the geofence radius {self.radius_m:.1f} m"
        if self.polygon and _polygon_signed_distance(self.polygon, x, y) < 0:
            return f"({x:.1f}, {y:.1f}) is outside the geofence polygon"
        return None


def parse_polygon(text: str) -> tuple[tuple[float, float], ...]:
    if not text.strip():
        return ()
    try:
        pts = tuple(tuple(float(v) for v in p.split(",")) for p in text.split(";") if p.strip())
    except ValueError:
        raise GeofenceError(f"geofence_polygon {text!r}: expected 'x1,y1;x2,y2;...'") from None
    if len(pts) < 3 or any(len(p) != 2 or not all(map(math.isfinite, p)) for p in pts):
        raise GeofenceError(f"geofence_polygon {text!r}: needs at least 3 finite x,y vertices")
    return pts  # type: ignore[return-value]


def _polygon_signed_distance(poly: Iterable[tuple[float, float]], x: float, y: float) -> float:
    """Distance to the polygon's edges, positive inside (even-odd rule), negative outside."""
    pts = list(poly)
    inside, best = False, math.inf
    for (x1, y1), (x2, y2) in zip(pts, pts[1:] + pts[:1]):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
        dx, dy = x2 - x1, y2 - y1
        t = 0.0 if dx == dy == 0 else max(0.0, min(1.0, ((x - x1) * dx + (y - y1) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(x - (x1 + t * dx), y - (y1 + t * dy)))
    return best if inside else -best
