"""Flight-mode names <-> autopilot custom modes: PX4, and ArduPilot copter for the same code path.

Our mode names (VehicleStatus.nav_state, VehicleState.flight_mode, fmu/srv/set_mode) are PX4's
navigation states: OFFBOARD, POSCTL, HOLD (= AUTO.LOITER), LAND, RTL, TAKEOFF, MISSION, ...

PX4 packs its mode into HEARTBEAT.custom_mode as a union {uint16 reserved; uint8 main_mode;
uint8 sub_mode}, i.e. custom_mode = main << 16 | sub << 24 (px4_custom_mode.h). Only AUTO and
POSCTL use sub modes. ArduPilot uses a plain mode number per vehicle type; for copters its GUIDED
plays the role of OFFBOARD and LOITER (or BRAKE) the role of HOLD.
"""
from __future__ import annotations

from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

__all__ = [
    "PX4_MAIN", "PX4_AUTO_SUB", "PX4_MODES", "ARDUCOPTER_MODES", "ARDUCOPTER_TO_OURS",
    "pack", "unpack", "encode", "decode", "Autopilot",
]

PX4_MAIN = {
    "MANUAL": 1, "ALTCTL": 2, "POSCTL": 3, "AUTO": 4, "ACRO": 5, "OFFBOARD": 6, "STABILIZED": 7,
    "TERMINATION": 10,
}
PX4_AUTO_SUB = {
    "READY": 1, "TAKEOFF": 2, "LOITER": 3, "MISSION": 4, "RTL": 5, "LAND": 6, "FOLLOW_TARGET": 8,
    "PRECLAND": 9, "VTOL_TAKEOFF": 10,
}

# our name -> (main, sub)
PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "ORBIT": (3, 1), "POSCTL_SLOW": (3, 2),
    "ACRO": (5, 0), "OFFBOARD": (6, 0), "STABILIZED": (7, 0), "TERMINATION": (10, 0),
    "READY": (4, 1), "TAKEOFF": (4, 2), "HOLD": (4, 3), "MISSION": (4, 4), "RTL": (4, 5),
    "LAND": (4, 6), "FOLLOW": (4, 8), "PRECLAND": (4, 9), "VTOL_TAKEOFF": (4, 10),
}
_PX4_BY_VALUE = {mm: name for name, mm in PX4_MODES.items()}

# ArduCopter mode numbers (ArduCopter/mode.h), by ArduPilot's own names.
ARDUCOPTER_NATIVE: dict[str, int] = {
    "STABILIZE": 0, "ACRO": 1, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6,
    "CIRCLE": 7, "LAND": 9, "DRIFT": 11, "SPORT": 13, "FLIP": 14, "AUTOTUNE": 15, "POSHOLD": 16,
    "BRAKE": 17, "THROW": 18, "AVOID_ADSB": 19, "GUIDED_NOGPS": 20, "SMART_RTL": 21,
    "FLOWHOLD": 22, "FOLLOW": 23, "ZIGZAG": 24, "SYSTEMID": 25, "AUTOROTATE": 26, "AUTO_RTL": 27,
    "TURTLE": 28,
}
# ArduPilot name -> ours, where one of ours means the same thing; the rest keep their own name.
ARDUCOPTER_TO_OURS = {
    "STABILIZE": "STABILIZED", "ALT_HOLD": "ALTCTL", "AUTO": "MISSION", "GUIDED": "OFFBOARD",
    "LOITER": "HOLD", "BRAKE": "HOLD", "POSHOLD": "POSCTL",
}
# our name -> ArduCopter number. HOLD -> LOITER (holds position and accepts a later GUIDED);
# BRAKE also decodes to HOLD. TAKEOFF has no copter mode (it is NAV_TAKEOFF in GUIDED).
ARDUCOPTER_MODES: dict[str, int] = {
    **{ARDUCOPTER_TO_OURS.get(n, n): v for n, v in ARDUCOPTER_NATIVE.items() if n != "BRAKE"},
    "BRAKE": ARDUCOPTER_NATIVE["BRAKE"],
}
_ARDUCOPTER_BY_VALUE = {v: ARDUCOPTER_TO_OURS.get(n, n) for n, v in ARDUCOPTER_NATIVE.items()}


def pack(main: int, sub: int = 0) -> int:
    """PX4 (main, sub) -> HEARTBEAT custom_mode."""
    return ((main & 0xFF) << 16) | ((sub & 0xFF) << 24)


def unpack(custom_mode: int) -> tuple[int, int]:
    """HEARTBEAT custom_mode -> PX4 (main, sub)."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def encode(name: str) -> int:
    """Our mode name -> PX4 custom_mode. KeyError for a name PX4 does not have."""
    return pack(*PX4_MODES[name.upper()])


def decode(custom_mode: int) -> str:
    """PX4 custom_mode -> our mode name; "PX4(main.sub)" for combinations we do not know.

    Main modes without sub modes ignore the sub byte, as PX4 itself does.
    """
    main, sub = unpack(custom_mode)
    if main not in (PX4_MAIN["AUTO"], PX4_MAIN["POSCTL"]):
        sub = 0
    return _PX4_BY_VALUE.get((main, sub), f"PX4({main}.{sub})")


@dataclass(frozen=True)
class Autopilot:
    """The mode map of one autopilot family, chosen from HEARTBEAT.autopilot.

    Anything that is not ArduPilot is treated as PX4 (the generic autopilot speaks no custom
    modes, and PX4's map is the stack's reference).
    """

    name: str  # "px4" or "ardupilot"
    mav_autopilot: int

    @classmethod
    def for_heartbeat(cls, mav_autopilot: int) -> "Autopilot":
        if mav_autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
            return cls("ardupilot", mav_autopilot)
        return cls("px4", mavlink.MAV_AUTOPILOT_PX4)

    @property
    def is_px4(self) -> bool:
        return self.name == "px4"

    def mode_names(self) -> list[str]:
        return list(PX4_MODES if self.is_px4 else ARDUCOPTER_MODES)

    def mode_name(self, custom_mode: int) -> str:
        """HEARTBEAT.custom_mode -> our mode name."""
        if self.is_px4:
            return decode(custom_mode)
        return _ARDUCOPTER_BY_VALUE.get(custom_mode, f"APM({custom_mode})")

    def custom_mode(self, name: str) -> int:
        """Our mode name -> HEARTBEAT/SET_MODE custom_mode; KeyError if this autopilot lacks it."""
        return encode(name) if self.is_px4 else ARDUCOPTER_MODES[name.upper()]

    def set_mode_params(self, name: str) -> tuple[float, float, float]:
        """MAV_CMD_DO_SET_MODE params 1-3 for our mode name (KeyError if unknown).

        PX4 takes (base_mode, main, sub); ArduPilot takes (base_mode, mode number, unused).
        """
        base = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        if self.is_px4:
            main, sub = PX4_MODES[name.upper()]
            return base, float(main), float(sub)
        return base, float(ARDUCOPTER_MODES[name.upper()]), 0.0

    def takeoff_param7(self, relative_alt_m: float, home_amsl_m: float) -> float:
        """MAV_CMD_NAV_TAKEOFF param7: PX4 wants altitude AMSL, ArduPilot altitude above home."""
        return home_amsl_m + relative_alt_m if self.is_px4 else relative_alt_m
