"""SafetyStatus: the safety service's one-line verdict on whether the vehicle may keep flying.

Requirement IF-2's SafetyStatus with every enum kept. Battery charge is a 0..1 fraction
(`battery_remaining`) as everywhere else in the stack, not the source's percent.
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, schema

__all__ = ["SafetyStatus"]


@schema("SafetyStatus", 1)
class SafetyStatus(Message, kw_only=True):
    """Overall safety level, component health, geofence, heartbeats (service liveliness), battery,
    and the action the safety service recommends (safety/status, 1 Hz)."""

    header: Header = msgspec.field(default_factory=Header)

    safety_level: int = 0
    LEVEL_NOMINAL = 0
    LEVEL_WARNING = 1
    LEVEL_CAUTION = 2
    LEVEL_EMERGENCY = 3

    estimator_healthy: bool = False
    controller_healthy: bool = False
    trajectory_healthy: bool = False
    px4_connected: bool = False
    gcs_connected: bool = False

    geofence_status: int = 0
    GEOFENCE_OK = 0
    GEOFENCE_WARNING = 1
    GEOFENCE_VIOLATION = 2
    distance_to_geofence_m: float | None = None  # None: no geofence configured

    heartbeats_alive: int = 0
    heartbeats_total: int = 0
    dead_heartbeats: list[str] = []

    battery_remaining: float | None = None  # 0..1, None when unknown
    battery_voltage_v: float | None = None
    battery_status: int = 0
    BATTERY_OK = 0
    BATTERY_WARNING = 1
    BATTERY_CRITICAL = 2

    active_warnings: list[str] = []
    active_errors: list[str] = []

    recommended_action: int = 0
    ACTION_NONE = 0
    ACTION_WARN = 1
    ACTION_HOLD = 2
    ACTION_RTH = 3
    ACTION_LAND = 4
    ACTION_EMERGENCY_STOP = 5
