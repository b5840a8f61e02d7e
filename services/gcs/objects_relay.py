"""Tracked objects -> ground stations (no Zenoh): a STATUSTEXT for each new confirmed object, each
lost one and each seen again, and every confirmed object as an ADSB_VEHICLE so QGroundControl and Mission Planner
draw it on their map under its label ("PERSON7").

Why ADSB_VEHICLE: it is the one common MAVLink message carrying a position that ground stations
draw on the map with a name, and it touches none of the vehicle's plans. The alternatives that
also show on a map are uploaded plans the autopilot acts on (mission items; rally points, which RTL
flies to; fence points), so an object must never become one of them. The contact says what it is:
emitter type POINT_OBSTACLE (a point on the ground, not traffic), geometric altitude, callsign from
class and track id, ICAO address from a block keyed by the track id. Ground stations drop ADS-B
contacts that are not refreshed within seconds, so confirmed objects are re-sent every
`refresh_s` while they are tracked and simply age out once lost.
"""
from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import ObjectEvent, TrackedObject, TrackedObjectArray

PREFIX = "Object: "
ICAO_BASE = 0xAE0000                  # + track id (16 bits): one stable contact per track
ADSB_FLAGS = (M.ADSB_FLAGS_VALID_COORDS | M.ADSB_FLAGS_VALID_ALTITUDE | M.ADSB_FLAGS_VALID_HEADING
              | M.ADSB_FLAGS_VALID_VELOCITY | M.ADSB_FLAGS_VALID_CALLSIGN)


def label(o: TrackedObject) -> str:
    return f"{o.class_name} #{o.track_id}"


def where(o: TrackedObject) -> str:
    if o.latitude_deg is not None and o.longitude_deg is not None:
        return f"{o.latitude_deg:.6f}, {o.longitude_deg:.6f}"
    return f"E {o.position_m.x:.1f} N {o.position_m.y:.1f} m"


def event_text(e: ObjectEvent) -> tuple[int, str] | None:
    """(severity, text) for an objects event: NOTICE for a new object, INFO for a lost one."""
    o = e.object
    if e.event == ObjectEvent.CONFIRMED:
        return M.MAV_SEVERITY_NOTICE, f"{PREFIX}{label(o)} at {where(o)} ({o.best_score:.2f})"
    if e.event == ObjectEvent.LOST:
        return M.MAV_SEVERITY_INFO, f"{PREFIX}{label(o)} lost at {where(o)}"
    if e.event == ObjectEvent.REACQUIRED:
        return M.MAV_SEVERITY_INFO, f"{PREFIX}{label(o)} seen again at {where(o)}"
    return None


def callsign(o: TrackedObject) -> bytes:
    """8 characters at most: the class (spaces dropped) cut to leave room for the track id."""
    ident = str(o.track_id)
    name = o.class_name.replace(" ", "").upper()[:max(0, 8 - len(ident))]
    return (name + ident)[:8].encode("ascii", "replace")


def adsb_contact(o: TrackedObject) -> M.MAVLink_adsb_vehicle_message | None:
    """The object as an ADS-B contact; None without a geodetic position (no home yet)."""
    if o.latitude_deg is None or o.longitude_deg is None:
        return None
    ve, vn, vu = o.velocity_mps.x, o.velocity_mps.y, o.velocity_mps.z
    heading_cdeg = int(round(math.degrees(math.atan2(ve, vn)) * 100)) % 36000
    return M.MAVLink_adsb_vehicle_message(
        ICAO_address=ICAO_BASE + (o.track_id & 0xFFFF), lat=int(round(o.latitude_deg * 1e7)),
        lon=int(round(o.longitude_deg * 1e7)), altitude_type=M.ADSB_ALTITUDE_TYPE_GEOMETRIC,
        altitude=int(round((o.altitude_amsl_m or 0.0) * 1000)), heading=heading_cdeg,
        hor_velocity=min(int(round(math.hypot(ve, vn) * 100)), 0xFFFF),
        ver_velocity=max(-32768, min(32767, int(round(vu * 100)))), callsign=callsign(o),
        emitter_type=M.ADSB_EMITTER_TYPE_POINT_OBSTACLE, tslc=0,
        flags=ADSB_FLAGS if o.altitude_amsl_m is not None else ADSB_FLAGS & ~M.ADSB_FLAGS_VALID_ALTITUDE,
        squawk=0)


class ObjectsRelay:
    """Which ADS-B contacts to send for each perception/objects: confirmed objects, each at most
    once per `refresh_s`."""

    def __init__(self, refresh_s: float = 1.0):
        self.refresh_s = refresh_s
        self.sent_s: dict[int, float] = {}

    def contacts(self, msg: TrackedObjectArray, now_s: float) -> list[M.MAVLink_adsb_vehicle_message]:
        out = []
        live = set()
        for o in msg.objects:
            if not o.confirmed:
                continue
            live.add(o.track_id)
            if now_s - self.sent_s.get(o.track_id, -math.inf) < self.refresh_s:
                continue
            m = adsb_contact(o)
            if m is not None:
                out.append(m)
                self.sent_s[o.track_id] = now_s
        self.sent_s = {k: v for k, v in self.sent_s.items() if k in live}
        return out
