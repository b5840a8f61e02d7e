"""The vehicle's outgoing MAVLink telemetry, like PX4's mavlink streams/: one builder per message
(what the simulated FC believes or measures, in NED/FRD), and the schedule that sends each at its
rate in sim time (SET_MESSAGE_INTERVAL changes a rate until the next reboot).

No sockets here (the runner moves the messages). ENU/FLU -> NED/FRD only through
services/mavlink/frames.py.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.mavlink import frames, px4

from .model import SimVehicle

M = mavlink
Message = mavlink.MAVLink_message

# Default stream rates (Hz) of the onboard link, in sim time, as PX4's onboard mode boots with
# them (lower than a bridge wants: local position 30 Hz, IMU 50 Hz, seen on PX4 SITL). They apply
# at boot and again after every reboot; SET_MESSAGE_INTERVAL changes them until the next one.
DEFAULT_RATES_HZ: dict[int, float] = {
    M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    M.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    M.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    M.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 1.0,
}

# GPS_RAW_INT of the simulated receiver with a fix (values of a good open-sky u-blox fix)
GPS_SATELLITES = 12
GPS_HDOP_X100 = 80
GPS_VDOP_X100 = 120
UINT16_UNKNOWN = 0xFFFF
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255  # 1.15.0 release, PX4's encoding
CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | M.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
SENSORS = (
    M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
    | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS
    | M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | M.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | M.MAV_SYS_STATUS_SENSOR_YAW_POSITION | M.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | M.MAV_SYS_STATUS_AHRS | M.MAV_SYS_STATUS_SENSOR_BATTERY | M.MAV_SYS_STATUS_PREARM_CHECK
)
MAG_NED_GAUSS = np.array([0.21, 0.01, 0.43])  # Earth field near the default home (Zurich)


class OnVehicle:
    """What the receiver, the streams and the module read of the vehicle alike."""

    vehicle: SimVehicle

    @property
    def commander(self):
        return self.vehicle.commander

    @property
    def now_s(self) -> float:
        return self.vehicle.time_s


class TelemetryStreams(OnVehicle):
    """Builds each telemetry message and says which are due; `builders` maps a message id to its
    builder (also what REQUEST_MESSAGE may ask for)."""

    def __init__(self, vehicle: SimVehicle, system_id: int, component_id: int):
        self.vehicle = vehicle
        self.system_id = system_id
        self.enc = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)  # message factory
        self.intervals_ns: dict[int, int] = {}
        self._next_due_ns: dict[int, int] = {}
        self._earliest_due_ns = 0   # no stream is due before this (0: look at them all)
        self._failsafes_seen = 0
        self.builders: dict[int, Callable[[], Message]] = {
            M.MAVLINK_MSG_ID_HEARTBEAT: self.heartbeat,
            M.MAVLINK_MSG_ID_SYS_STATUS: self.sys_status,
            M.MAVLINK_MSG_ID_BATTERY_STATUS: self.battery_status,
            M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self.extended_sys_state,
            M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self.local_position_ned,
            M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self.attitude_quaternion,
            M.MAVLINK_MSG_ID_ATTITUDE: self.attitude,
            M.MAVLINK_MSG_ID_HIGHRES_IMU: self.highres_imu,
            M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.global_position_int,
            M.MAVLINK_MSG_ID_HOME_POSITION: self.home_position,
            M.MAVLINK_MSG_ID_GPS_RAW_INT: self.gps_raw_int,
            M.MAVLINK_MSG_ID_ESTIMATOR_STATUS: self.estimator_status,
            M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.autopilot_version,
        }
        self.reset()

    def reset(self) -> None:
        """Boot defaults: every stream at its default rate, nothing sent yet."""
        self.intervals_ns = {mid: int(1e9 / hz) for mid, hz in DEFAULT_RATES_HZ.items()}
        self._next_due_ns.clear()
        self._earliest_due_ns = 0
        self._failsafes_seen = 0

    @property
    def time_boot_ms(self) -> int:
        return (self.vehicle.time_since_boot_ns // 1_000_000) & 0xFFFFFFFF

    @property
    def time_boot_us(self) -> int:
        return self.vehicle.time_since_boot_ns // 1000

    def due(self) -> list[Message]:
        """Telemetry due now (sim time), plus a STATUSTEXT when a failsafe fired."""
        now = self.vehicle.time_ns
        out = []
        if now >= self._earliest_due_ns:   # most physics steps (400 Hz) have nothing due: skip the scan
            earliest = None
            for mid, interval in self.intervals_ns.items():
                if interval <= 0:
                    continue
                due = self._next_due_ns.get(mid, now)
                if now >= due:
                    out.append(self.builders[mid]())
                    due += interval
                    due = self._next_due_ns[mid] = due if due > now else now + interval
                earliest = due if earliest is None or due < earliest else earliest
            self._earliest_due_ns = earliest if earliest is not None else now + 1
        if self.commander.counters["failsafes"] != self._failsafes_seen:
            self._failsafes_seen = self.commander.counters["failsafes"]
            out.append(self.statustext(M.MAV_SEVERITY_CRITICAL, f"Failsafe: {self.commander.failsafe_reason}"))
        return out

    def set_interval(self, mid: int, interval_us: float) -> bool:
        """SET_MESSAGE_INTERVAL: 0 = the default rate, < 0 = off; False for a message not streamed."""
        if mid not in self.builders or mid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return False
        if interval_us == 0:  # default rate
            hz = DEFAULT_RATES_HZ.get(mid, 0.0)
            self.intervals_ns[mid] = int(1e9 / hz) if hz > 0 else -1
        elif interval_us < 0:  # disable
            self.intervals_ns[mid] = -1
        else:
            self.intervals_ns[mid] = int(interval_us * 1000)
            self._next_due_ns.pop(mid, None)
        self._earliest_due_ns = 0
        return True

    def interval_us(self, mid: int) -> int | None:
        """GET_MESSAGE_INTERVAL's answer (-1: off); None for a message not streamed."""
        if mid not in self.builders:
            return None
        interval_ns = self.intervals_ns.get(mid, -1)
        return interval_ns // 1000 if interval_ns > 0 else -1

    def stream_rates_hz(self) -> dict[str, float]:
        """Current telemetry rates by message name (0: off), in sim time."""
        return {M.mavlink_map[mid].msgname: (1e9 / iv if iv > 0 else 0.0) for mid, iv in self.intervals_ns.items()}

    # ------------------------------------------------------------------ builders

    def statustext(self, severity: int, text: str) -> Message:
        return self.enc.statustext_encode(severity, text[:50].encode("ascii", "replace"))

    def heartbeat(self) -> Message:
        c = self.commander
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (M.MAV_MODE_FLAG_SAFETY_ARMED if c.armed else 0)
        if c.terminated:
            status = M.MAV_STATE_FLIGHT_TERMINATION
        elif c.failsafe:
            status = M.MAV_STATE_CRITICAL
        else:
            status = M.MAV_STATE_ACTIVE if c.armed else M.MAV_STATE_STANDBY
        return self.enc.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base, px4.encode(c.mode), status)

    def autopilot_version(self) -> Message:
        return self.enc.autopilot_version_encode(
            CAPABILITIES, PX4_VERSION, 0, 0, 0, list(b"aerosim\x00"), [0] * 8, [0] * 8, 0, 0,
            0x53494D0000000000 | self.system_id)

    def _noise(self, sigma: float, n: int = 3) -> np.ndarray:
        return self.vehicle.sensor_rng.normal(0.0, 1.0, n) * sigma

    def local_position_ned(self) -> Message:
        s, p = self.vehicle.estimate, self.vehicle.params   # what the FC believes (GPS-denied: vision + IMU)
        pos = frames.enu_to_ned(s.position_enu_m + self._noise(p.SIM_POS_NOISE))
        vel = frames.enu_to_ned(s.velocity_enu_mps + self._noise(p.SIM_VEL_NOISE))
        return self.enc.local_position_ned_encode(self.time_boot_ms, *pos, *vel)

    def _q_ned_frd(self) -> np.ndarray:
        return frames.q_enu_flu_to_ned_frd(self.vehicle.state.q_enu_flu)

    def attitude_quaternion(self) -> Message:
        rates = frames.flu_to_frd(self.vehicle.state.rates_flu_radps)
        return self.enc.attitude_quaternion_encode(self.time_boot_ms, *self._q_ned_frd(), *rates)

    def attitude(self) -> Message:
        roll, pitch, yaw = frames.quat_to_euler(self._q_ned_frd())
        rates = frames.flu_to_frd(self.vehicle.state.rates_flu_radps)
        return self.enc.attitude_encode(self.time_boot_ms, roll, pitch, yaw, *rates)

    def extended_sys_state(self) -> Message:
        return self.enc.extended_sys_state_encode(M.MAV_VTOL_STATE_UNDEFINED, self.commander.landed_state)

    def _battery_charge_state(self) -> int:
        rem, p = self.vehicle.airframe.battery.remaining, self.vehicle.params
        if rem < p.BAT_EMERGEN_THR:
            return M.MAV_BATTERY_CHARGE_STATE_EMERGENCY
        if rem < p.BAT_CRIT_THR:
            return M.MAV_BATTERY_CHARGE_STATE_CRITICAL
        if rem < p.BAT_LOW_THR:
            return M.MAV_BATTERY_CHARGE_STATE_LOW
        return M.MAV_BATTERY_CHARGE_STATE_OK

    def sys_status(self) -> Message:
        bat, c, p = self.vehicle.airframe.battery, self.commander, self.vehicle.params
        health = SENSORS
        if p.SIM_GPS_DENIED or not p.SIM_POS_VALID:
            health &= ~M.MAV_SYS_STATUS_SENSOR_GPS
        if not self.vehicle.estimator.valid(self.vehicle.time_ns):
            health &= ~(M.MAV_SYS_STATUS_SENSOR_GPS | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL)
        if c.arming_problem(self.now_s) and not c.armed:
            health &= ~M.MAV_SYS_STATUS_PREARM_CHECK
        if self._battery_charge_state() >= M.MAV_BATTERY_CHARGE_STATE_CRITICAL:
            health &= ~M.MAV_SYS_STATUS_SENSOR_BATTERY
        return self.enc.sys_status_encode(
            SENSORS, SENSORS, health, 200, int(bat.voltage_v * 1000), min(int(bat.current_a * 100), 32767),
            int(round(bat.remaining * 100)), 0, 0, 0, 0, 0, 0)

    def battery_status(self) -> Message:
        bat = self.vehicle.airframe.battery
        cap = self.vehicle.params.SIM_BAT_CAP
        remaining_s = int(bat.remaining * cap / max(bat.current_a, 0.1) * 3.6)
        voltages = [min(int(bat.voltage_v * 1000), 65534)] + [65535] * 9
        return self.enc.battery_status_encode(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, voltages,
            min(int(bat.current_a * 100), 32767), int(bat.used_mah), -1, int(round(bat.remaining * 100)),
            remaining_s, self._battery_charge_state())

    def highres_imu(self) -> Message:
        s, p = self.vehicle.state, self.vehicle.params
        acc = frames.flu_to_frd(s.specific_force_flu_mps2() + self._noise(p.SIM_ACC_NOISE))
        gyro = frames.flu_to_frd(s.rates_flu_radps + self._noise(p.SIM_GYRO_NOISE))
        mag = frames.quat_to_rotmat(self._q_ned_frd()).T @ MAG_NED_GAUSS
        alt_amsl = p.SIM_HOME_ALT + s.position_enu_m[2] + float(self._noise(p.SIM_BARO_NOISE, 1)[0])
        pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * alt_amsl) ** 5.25588  # ISA
        return self.enc.highres_imu_encode(self.time_boot_us, *acc, *gyro, *mag, pressure_hpa, 0.0,
                                           alt_amsl, 25.0, 0x1FFF)

    def global_position_int(self) -> Message:
        s, p = self.vehicle.estimate, self.vehicle.params
        pos = s.position_enu_m + self._noise(p.SIM_POS_NOISE)
        lat, lon = self.vehicle.home.reproject(north_m=pos[1], east_m=pos[0])
        vel_ned = frames.enu_to_ned(s.velocity_enu_mps)
        heading_deg = math.degrees(frames.yaw_enu_to_ned(s.yaw_rad)) % 360.0
        return self.enc.global_position_int_encode(
            self.time_boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)),
            int(round((p.SIM_HOME_ALT + pos[2]) * 1000)), int(round(pos[2] * 1000)),
            *(int(np.clip(round(v * 100), -32768, 32767)) for v in vel_ned), int(heading_deg * 100) % 36000)

    def gps_raw_int(self) -> Message:
        """The GPS receiver: a 3D fix of the true position (noise SIM_POS_NOISE, reported as its
        accuracy) with GPS, no fix and no satellites when GPS-denied (jammed / indoors)."""
        p = self.vehicle.params
        if self.vehicle.estimator.gps_denied:
            return self.enc.gps_raw_int_encode(self.time_boot_us, M.GPS_FIX_TYPE_NO_FIX, 0, 0, 0,
                                               UINT16_UNKNOWN, UINT16_UNKNOWN, UINT16_UNKNOWN, UINT16_UNKNOWN, 0)
        s = self.vehicle.state
        pos = s.position_enu_m + self._noise(p.SIM_POS_NOISE)
        lat, lon = self.vehicle.home.reproject(north_m=pos[1], east_m=pos[0])
        vel_ned = frames.enu_to_ned(s.velocity_enu_mps)
        cog_deg = math.degrees(math.atan2(vel_ned[1], vel_ned[0])) % 360.0
        acc_mm = max(1, int(round(p.SIM_POS_NOISE * 1000)))
        return self.enc.gps_raw_int_encode(
            self.time_boot_us, M.GPS_FIX_TYPE_3D_FIX, int(round(lat * 1e7)), int(round(lon * 1e7)),
            int(round((p.SIM_HOME_ALT + pos[2]) * 1000)), GPS_HDOP_X100, GPS_VDOP_X100,
            min(int(round(math.hypot(vel_ned[0], vel_ned[1]) * 100)), UINT16_UNKNOWN - 1),
            int(round(cog_deg * 100)) % 36000, GPS_SATELLITES, 0, acc_mm, acc_mm, 0, 0, 0)

    def estimator_status(self) -> Message:
        """ESTIMATOR_STATUS as PX4's EKF2 sets it: attitude, velocity and baro height always; a
        horizontal position relative only (vision) when GPS-denied, absolute with GPS; none (and
        constant-position mode) when the estimator has no valid position."""
        est, p = self.vehicle.estimator, self.vehicle.params
        flags = (M.ESTIMATOR_ATTITUDE | M.ESTIMATOR_VELOCITY_VERT | M.ESTIMATOR_POS_VERT_ABS
                 | M.ESTIMATOR_POS_VERT_AGL)
        if est.valid(self.vehicle.time_ns):
            flags |= M.ESTIMATOR_VELOCITY_HORIZ | M.ESTIMATOR_POS_HORIZ_REL | M.ESTIMATOR_PRED_POS_HORIZ_REL
            if not est.gps_denied:
                flags |= M.ESTIMATOR_POS_HORIZ_ABS | M.ESTIMATOR_PRED_POS_HORIZ_ABS
        else:
            flags |= M.ESTIMATOR_CONST_POS_MODE
        horiz_m = est.position_sigma_m() if est.gps_denied else p.SIM_POS_NOISE
        nan = float("nan")   # innovation test ratios: not modelled
        return self.enc.estimator_status_encode(self.time_boot_us, flags, nan, nan, nan, nan, nan, nan,
                                                horiz_m, p.SIM_BARO_NOISE)

    def home_position(self) -> Message:
        p = self.vehicle.params
        return self.enc.home_position_encode(
            int(round(p.SIM_HOME_LAT * 1e7)), int(round(p.SIM_HOME_LON * 1e7)), int(round(p.SIM_HOME_ALT * 1000)),
            0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.time_boot_us)
