"""Flight-controller parameter sets the stack needs, each value with its reason, and how they are
applied to a PX4 over MAVLink and read back.

One home for them: `aero up --profile px4 --gps-denied` boots PX4 SITL with SETS["gps-denied-sih"]
(tools/cli/px4_sitl.py), `aero fc params apply gps-denied --fcu-url ...` sets SETS["gps-denied"] on a
connected flight controller (a real vehicle) and reads each back, and docs/px4.md's "GPS-denied on
PX4's EKF2" table lists the same values.

Values are PX4's (v1.14+ numbering: EKF2_EV_CTRL bits, NAV_RCL_ACT 3 = Land). Integer parameters go
over MAVLink bytewise (PX4's MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): the int32's bytes in
PARAM_SET's float field.
"""
from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

INT32, REAL32 = mavlink.MAV_PARAM_TYPE_INT32, mavlink.MAV_PARAM_TYPE_REAL32


@dataclass(frozen=True)
class FcParam:
    name: str
    value: int | float
    why: str

    @property
    def param_type(self) -> int:
        return INT32 if isinstance(self.value, int) else REAL32

    @property
    def text(self) -> str:
        return f"{self.value:g}" if isinstance(self.value, float) else str(self.value)


# EKF2_EV_DELAY is how far a vision stamp is off the IMU's clock, not how old a pose is on arrival:
# EKF2 subtracts it from each stamp and fuses the sample once its fusion horizon (EKF2_DELAY_MAX,
# 200 ms) reaches it. Our stamps are on PX4's IMU clock already: vio stamps each pose at an IMU sample
# of PX4's own (images at the ground truth beside it: -11..+1 ms off PX4's gyro, diagnostics/sim
# truth_imu_lag_ms), and fmu answers PX4's TIMESYNC in that clock, so PX4 maps the stamp into its own
# time once its sync has converged. Measured on PX4 (tests/integration/test_px4_gps_denied.py, village
# survey on our VIO): a pose is 7 ms old at PX4 (median; IMU-propagated poses between frames), inside
# the horizon; the stamp error is below one EKF2 step (10 ms). So the delay to add is zero.
EV_DELAY_MS = 0.0

GPS_DENIED: list[FcParam] = [
    FcParam("EKF2_GPS_CTRL", 0, "no GNSS aiding at all (position, velocity, height, yaw), even when a "
                                "receiver gets a fix: a jammed or spoofed fix must not pull the estimate"),
    FcParam("EKF2_EV_CTRL", 7, "external vision: horizontal position (1) + vertical position (2) + velocity (4); "
                               "not yaw (8): the VIO's yaw is relative to where it started and drifts, so heading "
                               "stays the magnetometer's and EKF2 rotates the vision frame (ODOMETRY frame_id "
                               "LOCAL_FRD) onto its own"),
    FcParam("EKF2_HGT_REF", 3, "vision is the height reference (0 baro, 1 GNSS, 2 range, 3 vision): the baro "
                               "drifts with weather and prop wash; it stays fused with its offset estimated"),
    FcParam("EKF2_EV_DELAY", EV_DELAY_MS, "ms; how far vision stamps are off PX4's IMU clock: each pose is stamped "
                                          "at an IMU sample of PX4's own and mapped by TIMESYNC (answered in that "
                                          "clock), measured -11..+1 ms, under one EKF2 step; the pose's age on arrival "
                                          "(7 ms median measured) is covered by EKF2_DELAY_MAX (200 ms), not by this"),
    FcParam("EKF2_EV_NOISE_MD", 1, "vision noise from EKF2_EVP_NOISE / EKF2_EVV_NOISE, not the message: our "
                                   "VIO's covariance includes the drift accumulated since it started (a slowly "
                                   "varying offset, not noise per sample), which would make EKF2 trust vision "
                                   "less and dead-reckon on the IMU more the longer it flies"),
    FcParam("EKF2_EVP_NOISE", 0.1, "m; 1-sigma vision position noise per sample (PX4's default; the VIO's "
                                   "frame-to-frame jitter is a few cm)"),
    FcParam("EKF2_EVV_NOISE", 0.1, "m/s; 1-sigma vision velocity noise per sample (PX4's default)"),
    FcParam("EKF2_EV_QMIN", 50, "vision below this quality is not fused: the VIO sends 50-100 while TRACKING, "
                                "1-49 while DEGRADED (poses carried forward on the IMU keep their frame's); "
                                "EKF2 stops following a degrading VIO and PX4's no-position failsafe acts, "
                                "instead of flying on it (at load 20-40 a diverged VIO took the vehicle 84-249 m "
                                "off with 0)"),
    FcParam("COM_RCL_EXCEPT", 4, "OFFBOARD is exempt from the RC-loss failsafe: the companion keeps flying "
                                 "(its own policy holds or lands) when a pilot's radio drops out"),
    FcParam("NAV_RCL_ACT", 3, "RC loss outside OFFBOARD: Land (1 Hold, 2 Return, 3 Land); Return would fly to "
                              "home on the vision estimate, which has drifted by then and stops with the cameras"),
    FcParam("GF_ACTION", 1, "geofence breach: warn only (0 none, 1 warning, 2 hold, 3 return, 4 terminate, "
                            "5 land); without GNSS the fence's position is the vision estimate's, which drifts"),
    FcParam("MC_YAWRATE_MAX", 60.0, "deg/s; slow turns keep the VIO's features in both cameras and unblurred "
                                    "(a fast yaw sweeps the scene out of view: VIO degrades or is lost)"),
]

# PX4 SITL's SIH quadrotor only: its simulated receiver sees no satellites, like a GPS under a roof
# or jammed (the receiver is there, with no fix; SENS_EN_GPSSIM 0 would remove it); its world at 0 m.
SIH_GPS_OFF = [
    FcParam("SIM_GPS_USED", 0, "SIH: the simulated GPS receiver sees 0 satellites (no fix)"),
    FcParam("SIH_LOC_H0", 0.0, "m AMSL; SIH's world at sea level, so the local origin fmu gives PX4 (global_origin, "
                               "altitude 0) is SIH's own: this EKF2 moves its local height by the origin's altitude "
                               "when one is set, which with vision as the height reference would put the vehicle "
                               "hundreds of metres underground"),
]

SETS: dict[str, list[FcParam]] = {"gps-denied": GPS_DENIED, "gps-denied-sih": GPS_DENIED + SIH_GPS_OFF}


def encode(p: FcParam) -> float:
    """PARAM_SET's float field: a REAL32 as itself, an INT32's bytes (bytewise encoding)."""
    if p.param_type == INT32:
        return struct.unpack("<f", struct.pack("<i", int(p.value)))[0]
    return float(p.value)


def decode(param_value: float, param_type: int) -> int | float:
    if param_type == INT32:
        return struct.unpack("<i", struct.pack("<f", param_value))[0]
    return float(param_value)


def matches(p: FcParam, read: int | float | None) -> bool:
    if read is None:
        return False
    if p.param_type == INT32:
        return read == p.value
    return math.isclose(float(read), float(p.value), rel_tol=1e-5, abs_tol=1e-6)


@dataclass
class Row:
    """One parameter's outcome: what was wanted and what the FC says it now holds (None: no answer,
    e.g. a parameter this firmware does not have)."""

    param: FcParam
    read_back: int | float | None = None

    @property
    def ok(self) -> bool:
        return matches(self.param, self.read_back)


def apply(conn, target_system: int, params: list[FcParam], timeout_s: float = 2.0, retries: int = 3) -> list[Row]:
    """PARAM_SET each parameter and wait for the PARAM_VALUE PX4 answers with (the value it now
    holds); re-sent up to `retries` times. Then PARAM_REQUEST_READ each once more, so the table shows
    what the FC holds, not what it echoed."""
    rows = [Row(p) for p in params]
    for row in rows:
        for _ in range(retries):
            conn.mav.param_set_send(target_system, 1, row.param.name.encode(), encode(row.param), row.param.param_type)
            got = _await_value(conn, row.param.name, timeout_s)
            if got is not None and matches(row.param, got):
                break
    for row in rows:
        for _ in range(retries):
            conn.mav.param_request_read_send(target_system, 1, row.param.name.encode(), -1)
            row.read_back = _await_value(conn, row.param.name, timeout_s)
            if row.read_back is not None:
                break
    return rows


def _await_value(conn, name: str, timeout_s: float) -> int | float | None:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=min(left, 0.2))
        if m is not None and str(m.param_id).rstrip("\x00") == name:
            return decode(m.param_value, m.param_type)
    return None


def boot_env(params: list[FcParam]) -> dict[str, str]:
    """The set as PX4 SITL boot parameters (PX4_PARAM_<NAME>=<value>, applied by PX4's rcS)."""
    return {f"PX4_PARAM_{p.name}": p.text for p in params}
