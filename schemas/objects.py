"""Tracked objects in the world: what the objects service makes of per-image detections.

A ground station or the autonomy wants "a person at lat/lon, seen 12 s ago, track 7", not boxes in
one image. Positions are ENU metres in the local frame (`header.frame_id`, e.g. "map"); the 3x3
covariances are plain row-major lists of 9 floats (small enough that any msgpack reader takes them
as they are). lat/lon/alt are about the flight controller's home and None until a home is known.
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema
from .geometry import Vector3

__all__ = ["TrackedObject", "TrackedObjectArray", "ObjectEvent"]


class TrackedObject(msgspec.Struct, kw_only=True):
    """One track: its class, where it is (centre of the object, ENU) and how sure we are."""

    track_id: int = 0
    class_name: str = ""
    class_id: int = 0
    confirmed: bool = False
    position_m: Vector3 = msgspec.field(default_factory=Vector3)
    position_covariance_m2: list[float] = []        # 3x3 row-major, ENU
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
    first_seen_ns: int = 0                          # image stamps
    last_seen_ns: int = 0
    hits: int = 0
    best_score: float = 0.0
    range_m: float = 0.0                            # camera to object at the last detection
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_amsl_m: float | None = None


@schema("TrackedObjectArray", 1)
class TrackedObjectArray(Message, kw_only=True):
    """perception/objects: every live track after one detection frame (`header.stamp_ns` is the
    image's stamp)."""

    header: Header = msgspec.field(default_factory=Header)
    objects: list[TrackedObject] = []


@schema("ObjectEvent", 1)
class ObjectEvent(Message, kw_only=True):
    """perception/objects/events: a track became confirmed (a new object), was lost (unseen for
    the track timeout) or was reacquired (a lost object seen again, same id); `object` is the
    track as it was at that moment."""

    header: Header = msgspec.field(default_factory=Header)
    event: str = ""
    object: TrackedObject = msgspec.field(default_factory=TrackedObject)

    CONFIRMED = "confirmed"
    LOST = "lost"
    REACQUIRED = "reacquired"
