"""Ground-station link messages, published by the gcs service (requirements GCS-1 - GCS-4).

GcsLink replaces the source's implicit "GCS alive" check (its HEARTBEAT handler, GCS-3) with an explicit
state: `connected` turns False when no ground-station HEARTBEAT arrived for the timeout
(3.5 s by default); the mission manager may treat that as link loss.
Joystick replaces the source's /mav/joystick (geometry_msgs/TwistStamped carrying MANUAL_CONTROL):
the axes are MAVLink's, normalised to -1..1 (throttle 0..1), not physical velocities.
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema
from ._checks import check_finite

__all__ = ["GcsLink", "Joystick"]


@schema("GcsLink", 1)
class GcsLink(Message, kw_only=True):
    """gcs/link: whether a ground station is heard (published on change and at 1 Hz)."""

    header: Header = msgspec.field(default_factory=Header)
    connected: bool = False
    address: str = ""                   # "ip:port" of the ground station, "" before any packet
    system_id: int = 0                  # the ground station's MAVLink system id (0 = none yet)
    last_heartbeat_age_s: float | None = None  # None before any heartbeat
    packets_received: int = 0
    packets_invalid: int = 0


@schema("Joystick", 1)
class Joystick(Message, kw_only=True):
    """gcs/joystick: one MANUAL_CONTROL from the ground station, axes normalised.

    x = pitch (forward +), y = roll (right +), z = throttle (0..1), r = yaw (clockwise +),
    as MAVLink defines them (-1000..1000, z 0..1000) divided by 1000. `buttons` is the bitmask.
    """

    header: Header = msgspec.field(default_factory=Header)
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    r: float = 0.0
    buttons: int = 0
    source_system: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("x", "y", "z", "r"):
            check_finite(name, getattr(self, name))
