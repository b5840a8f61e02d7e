"""The flight controller's GPS receiver and estimator health, MAVLink -> ENU/SI schemas (no Zenoh).

GPS_RAW_INT -> GpsPosition (fmu/out/vehicle_gps_position), ESTIMATOR_STATUS -> EstimatorStatus
(fmu/out/estimator_status): what a ground station needs to see whether there is a GPS fix and
whether the position is absolute (GPS) or relative only (vision). MAVLink's "unknown" sentinels
(UINT16_MAX, UINT8_MAX, NaN) become None, never a fake number.
"""
from __future__ import annotations

import math

from aeroperception.schemas import EstimatorStatus, GpsPosition, Header
from aeroperception.services.mavlink import frames

UINT16_UNKNOWN = 0xFFFF
UINT8_UNKNOWN = 0xFF


def _known(value: int, scale: float, unknown: int = UINT16_UNKNOWN) -> float | None:
    return None if value == unknown else value * scale


def _accuracy_m(value_mm: int) -> float | None:
    return value_mm / 1000.0 if value_mm > 0 else None   # extension field: 0 when not sent


def gps_from_mavlink(m, stamp_ns: int) -> GpsPosition:
    """GPS_RAW_INT (degE7, mm AMSL, HDOP x100, cm/s, course cdeg from North clockwise) ->
    GpsPosition (degrees, m, ENU course). Position only with a fix (fix_type >= 2)."""
    fix = int(m.fix_type) if 0 <= m.fix_type <= 8 else GpsPosition.FIX_NO_FIX
    has_fix = fix >= GpsPosition.FIX_2D
    cog = _known(m.cog, 0.01)
    return GpsPosition(
        header=Header(stamp_ns=stamp_ns, frame_id="wgs84"), fix_type=fix,
        latitude_deg=m.lat / 1e7 if has_fix else None, longitude_deg=m.lon / 1e7 if has_fix else None,
        altitude_amsl_m=m.alt / 1e3 if fix >= GpsPosition.FIX_3D else None,
        hdop=_known(m.eph, 0.01), vdop=_known(m.epv, 0.01),
        horizontal_accuracy_m=_accuracy_m(getattr(m, "h_acc", 0)),
        vertical_accuracy_m=_accuracy_m(getattr(m, "v_acc", 0)),
        ground_speed_mps=_known(m.vel, 0.01),
        course_rad=None if cog is None else math.remainder(frames.yaw_ned_to_enu(math.radians(cog)), math.tau),
        satellites_visible=None if m.satellites_visible == UINT8_UNKNOWN else int(m.satellites_visible))


def _ratio(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def estimator_status_from_mavlink(m, stamp_ns: int) -> EstimatorStatus:
    """ESTIMATOR_STATUS -> EstimatorStatus: flags as sent, ratios and accuracies (m) None when NaN."""
    return EstimatorStatus(
        header=Header(stamp_ns=stamp_ns), flags=int(m.flags),
        velocity_test_ratio=_ratio(m.vel_ratio), position_horizontal_test_ratio=_ratio(m.pos_horiz_ratio),
        position_vertical_test_ratio=_ratio(m.pos_vert_ratio), magnetometer_test_ratio=_ratio(m.mag_ratio),
        height_above_ground_test_ratio=_ratio(m.hagl_ratio), airspeed_test_ratio=_ratio(m.tas_ratio),
        position_horizontal_accuracy_m=_ratio(m.pos_horiz_accuracy),
        position_vertical_accuracy_m=_ratio(m.pos_vert_accuracy))
