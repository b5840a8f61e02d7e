"""Flight-mode names <-> autopilot custom modes, for PX4 and ArduPilot copter.

Our names (what VehicleState.flight_mode and fmu/srv/set_mode speak) are PX4's: OFFBOARD,
POSCTL, HOLD (= AUTO.LOITER), LAND, RTL, TAKEOFF, MISSION, ... PX4 packs its mode as
custom_mode = main << 16 | sub << 24; ArduPilot uses a plain mode number, and its GUIDED plays
the role of OFFBOARD.
"""
from __future__ import annotations

from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

PX4_MAIN = {"MANUAL": 1, "ALTCTL": 2, "POSCTL": 3, "AUTO": 4, "ACRO": 5, "OFFBOARD": 6, "STABILIZED": 7}
PX4_AUTO_SUB = {"READY": 1, "TAKEOFF": 2, "LOITER": 3, "MISSION": 4, "RTL": 5, "LAND": 6, "FOLLOW": 8,
                "PRECLAND": 9}
# our name -> (main, sub)
PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "ACRO": (5, 0), "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0), "READY": (4, 1), "TAKEOFF": (4, 2), "HOLD": (4, 3), "MISSION": (4, 4),
    "RTL": (4, 5), "LAND": (4, 6), "FOLLOW": (4, 8), "PRECLAND": (4, 9),
}
ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZED": 0, "ACRO": 1, "ALTCTL": 2, "MISSION": 3, "OFFBOARD": 4, "HOLD": 5, "RTL": 6,
    "CIRCLE": 7, "LAND": 9, "DRIFT": 11, "SPORT": 13, "FLIP": 14, "AUTOTUNE": 15, "POSCTL": 16,
    "BRAKE": 17, "THROW": 18, "SMART_RTL": 21,
}
ARDUPILOT_NATIVE = {"OFFBOARD": "GUIDED", "HOLD": "LOITER", "MISSION": "AUTO", "POSCTL": "POSHOLD",
                    "ALTCTL": "ALT_HOLD", "STABILIZED": "STABILIZE"}


def px4_custom_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


def px4_split(custom_mode: int) -> tuple[int, int]:
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def px4_encode(name: str) -> int:
    """Our mode name -> PX4 custom_mode; KeyError for unknown names."""
    return px4_custom_mode(*PX4_MODES[name.upper()])


def px4_decode(custom_mode: int) -> str:
    main, sub = px4_split(custom_mode)
    for name, (m, s) in PX4_MODES.items():
        if m == main and (s == sub or (m != 4 and s == 0)):
            return name
    return f"PX4({main}.{sub})"


@dataclass(frozen=True)
class Autopilot:
    """Mode mapping of one autopilot family, chosen from HEARTBEAT.autopilot."""

    name: str
    mav_autopilot: int

    @classmethod
    def for_heartbeat(cls, mav_autopilot: int) -> "Autopilot":
        if mav_autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
            return cls("ardupilot", mav_autopilot)
        return cls("px4", mavlink.MAV_AUTOPILOT_PX4)

    def mode_names(self) -> list[str]:
        return list(PX4_MODES if self.name == "px4" else ARDUCOPTER_MODES)

    def mode_name(self, custom_mode: int) -> str:
        if self.name == "px4":
            return px4_decode(custom_mode)
        for name, num in ARDUCOPTER_MODES.items():
            if num == custom_mode:
                return name
        return f"APM({custom_mode})"

    def custom_mode(self, name: str) -> int:
        name = name.upper()
        return px4_encode(name) if self.name == "px4" else ARDUCOPTER_MODES[name]

    def set_mode_params(self, name: str) -> tuple[float, float, float]:
        """MAV_CMD_DO_SET_MODE params 1-3 for our mode name (KeyError if unknown)."""
        name = name.upper()
        base = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        if self.name == "px4":
            main, sub = PX4_MODES[name]
            return base, float(main), float(sub)
        return base, float(ARDUCOPTER_MODES[name]), 0.0
