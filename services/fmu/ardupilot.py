"""Where ArduCopter answers fmu's input differently from PX4, free of sockets and Zenoh: the one place
fmu asks "which autopilot?" for flying (mode names are services/mavlink/px4's Autopilot).
tests/unit/test_fmu_ardupilot.py pins each difference.

1. Set-point masks. ArduCopter's GUIDED (GCS_Mavlink.cpp handle_message_set_position_target_local_ned)
   takes position, velocity, acceleration, position+velocity(+acceleration), velocity+acceleration;
   position with acceleration but no velocity is "not valid" and re-initialises GUIDED (the vehicle
   stops where it is). PX4 adds that acceleration as feed-forward. For ArduPilot the acceleration of a
   position-only set-point is dropped (the position is what was asked).
2. Take-off. PX4 in OFFBOARD climbs off the ground on a position set-point; ArduCopter in GUIDED keeps
   a landed vehicle on the ground (make_safe_ground_handling) until MAV_CMD_NAV_TAKEOFF (param7: metres
   above home) clears its land-complete flag, and disarms it after DISARM_DELAY (10 s) if it does not
   leave the ground. So while ArduPilot is armed in GUIDED, on the ground, and the set-point asks to
   climb, fmu sends NAV_TAKEOFF (at most once a TAKEOFF_RESEND_S) instead of the set-point, to
   TAKEOFF_CLEAR_M; once its EXTENDED_SYS_STATE says IN_AIR, the set-points go through again and its
   position controller flies the planner's climb from there.
3. Ready to arm. PX4 says so in its log ("Ready for takeoff"); ArduPilot refuses arming until EKF3 uses
   GPS (~40 s after SITL starts). Its SYS_STATUS pre-arm bit (MAV_SYS_STATUS_PREARM_CHECK healthy) turns
   on earlier (measured: 24 s, GPS in use at 41 s), so fmu's health value `ready_to_arm` is that bit
   and ArduPilot's own "EKF3 IMU<n> is using GPS" seen; a caller waits for it (bounded) before arming.
4. Guided timeout. ArduCopter stops a vehicle flown by velocity or acceleration set-points that have not
   been renewed within GUID_TIMEOUT (3 s); a position set-point is held without limit. fmu's stream
   (offboard_rate_hz, and its brake-and-hold when the planner goes quiet) keeps it renewed; nothing to
   send differently.
5. Console text. ArduPilot prints its boot console ("Init ArduCopter ...", "Init Gyro***") on SERIAL0
   before and between its first MAVLink packets, at every start: printable text where MAVLink is
   expected. fmu counts it (`fc_console_bytes`) instead of reporting bad input (which would leave fmu's
   health WARN for the whole run); any other bad data still is.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import LandedState

from .logic import IGNORE_ACC, IGNORE_POS, IGNORE_VEL

TAKEOFF_CLEAR_M = 2.0       # NAV_TAKEOFF's altitude above home: enough to leave the ground, then set-points
TAKEOFF_CLIMB_M = 0.2       # a set-point this far above the vehicle asks it to leave the ground,
TAKEOFF_CLIMB_MPS = 0.1     # or one asking to climb at least this fast
TAKEOFF_RESEND_S = 1.0
PREARM_BIT = mavlink.MAV_SYS_STATUS_PREARM_CHECK
_EKF_GPS = re.compile(r"EKF3 IMU\d+ is using GPS")


def setpoint_mask(type_mask: int) -> int:
    """SET_POSITION_TARGET_LOCAL_NED type_mask as ArduCopter accepts it (difference 1)."""
    has_pos, has_vel, has_acc = not type_mask & IGNORE_POS, not type_mask & IGNORE_VEL, not type_mask & IGNORE_ACC
    if has_pos and not has_vel and has_acc:
        return type_mask | IGNORE_ACC
    return type_mask


def adapt_target(f: dict) -> dict:
    """setpoint_target's fields for ArduPilot: the mask fixed, dropped parts sent as zeros."""
    mask = setpoint_mask(f["type_mask"])
    if mask == f["type_mask"]:
        return f
    return dict(f, type_mask=mask, afx=0.0, afy=0.0, afz=0.0)


def prearm_ok(m) -> bool:
    """SYS_STATUS: ArduPilot's pre-arm checks pass (difference 3)."""
    return bool(m.onboard_control_sensors_present & PREARM_BIT and m.onboard_control_sensors_health & PREARM_BIT)


def console_text(data: bytes, is_px4: bool, heard_heartbeat: bool) -> bool:
    """Difference 5: undecodable bytes that are ArduPilot's console text (printable ASCII and
    whitespace), from an ArduPilot or from an FC not yet identified by its heartbeat."""
    return (not is_px4 or not heard_heartbeat) and bool(data) and all(b in _TEXT for b in data)


_TEXT = frozenset(range(0x20, 0x7F)) | {0x09, 0x0A, 0x0D}


def ekf_uses_gps(statustext: str) -> bool:
    """ArduPilot's STATUSTEXT when an EKF core starts fusing GPS (AP_NavEKF3_Control.cpp)."""
    return bool(_EKF_GPS.match(statustext))


def ready_to_arm(is_px4: bool, prearm: bool, uses_gps: bool) -> bool | None:
    """Difference 3; None for PX4 (its readiness is in its own log)."""
    return None if is_px4 else prearm and uses_gps


@dataclass
class GuidedTakeoff:
    """Difference 2: whether a set-point goes to ArduPilot, or NAV_TAKEOFF instead. Times are
    monotonic seconds; `up_m` heights are ENU metres in fmu's local frame. A landed state ArduPilot
    has not reported (UNDEFINED) forwards the set-point, as for PX4."""

    last_sent_s: float = -1e9
    sent: int = 0

    def command(self, now_s: float, armed: bool, mode: str, landed_state: int, vehicle_up_m: float,
                setpoint_up_m: float | None, setpoint_up_mps: float | None = None) -> tuple[bool, tuple[float, ...] | None]:
        """(forward the set-point?, NAV_TAKEOFF params to send now or None). None: not in the set-point."""
        on_ground = landed_state == LandedState.ON_GROUND
        climbing = ((setpoint_up_m is not None and setpoint_up_m > vehicle_up_m + TAKEOFF_CLIMB_M)
                    or (setpoint_up_mps is not None and setpoint_up_mps > TAKEOFF_CLIMB_MPS))
        if not (armed and mode == "OFFBOARD" and on_ground and climbing):
            return True, None
        if now_s - self.last_sent_s < TAKEOFF_RESEND_S:
            return False, None
        self.last_sent_s, self.sent = now_s, self.sent + 1
        return False, (0.0, 0.0, 0.0, float("nan"), 0.0, 0.0, TAKEOFF_CLEAR_M)
