"""The vehicle's MAVLink side, like PX4's mavlink module on its onboard link.

`handle(msg)` turns one received message into commander calls and returns the replies
(COMMAND_ACK for every command addressed to us, TIMESYNC, PARAM_VALUE, ...); `tick()` returns
the telemetry streams that are due at the current sim time. No sockets here: the runner moves
the messages, so this is testable with plain message objects.

This is the only place in the simulator that sees NED/FRD; every conversion goes through
services/mavlink/frames.py.
"""
from __future__ import annotations

import logging
import math
import time
from collections import Counter
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.mavlink import frames, ftp, px4
from aeroperception.services.mavlink.param_value import float_bits_to_int, int_to_float_bits
from aeroperception.services.runtime.params import ParamError

from .commander import ACCEPTED, DENIED, Ack
from .control import Setpoint
from .model import SimVehicle

log = logging.getLogger("aeroperception.sim.vehicle")

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
FORCE_MAGIC = 21196  # COMPONENT_ARM_DISARM param2: skip checks (PX4, ArduPilot)
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

# SET_POSITION_TARGET type_mask bits (POSITION_TARGET_TYPEMASK)
_IGNORE_POS = (M.POSITION_TARGET_TYPEMASK_X_IGNORE, M.POSITION_TARGET_TYPEMASK_Y_IGNORE,
               M.POSITION_TARGET_TYPEMASK_Z_IGNORE)
_IGNORE_VEL = (M.POSITION_TARGET_TYPEMASK_VX_IGNORE, M.POSITION_TARGET_TYPEMASK_VY_IGNORE,
               M.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
_IGNORE_ACC = (M.POSITION_TARGET_TYPEMASK_AX_IGNORE, M.POSITION_TARGET_TYPEMASK_AY_IGNORE,
               M.POSITION_TARGET_TYPEMASK_AZ_IGNORE)


def _masked_ned(values, type_mask: int, bits) -> np.ndarray:
    """NED triple with the axes the type_mask ignores set to NaN, converted to ENU."""
    ned = np.array([math.nan if type_mask & bit else float(v) for v, bit in zip(values, bits)])
    return frames.ned_to_enu(ned)


def setpoint_from_mavlink(m) -> Setpoint | None:
    """SET_POSITION_TARGET_LOCAL_NED -> ENU Setpoint, honouring type_mask like PX4; None for
    frames other than MAV_FRAME_LOCAL_NED."""
    if m.coordinate_frame != M.MAV_FRAME_LOCAL_NED:
        return None
    tm = m.type_mask
    accel_bits = _IGNORE_ACC if not tm & M.POSITION_TARGET_TYPEMASK_FORCE_SET else (0xFFFF,) * 3
    return Setpoint(
        position_enu_m=_masked_ned((m.x, m.y, m.z), tm, _IGNORE_POS),
        velocity_enu_mps=_masked_ned((m.vx, m.vy, m.vz), tm, _IGNORE_VEL),
        accel_enu_mps2=_masked_ned((m.afx, m.afy, m.afz), tm, accel_bits),
        yaw_rad=math.nan if tm & M.POSITION_TARGET_TYPEMASK_YAW_IGNORE or not math.isfinite(m.yaw)
        else frames.yaw_ned_to_enu(m.yaw),
        yaw_rate_radps=math.nan if tm & M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
        else frames.yaw_rate_ned_to_enu(m.yaw_rate),
    )


class MavlinkModule:
    def __init__(self, vehicle: SimVehicle, system_id: int = 1, component_id: int = M.MAV_COMP_ID_AUTOPILOT1):
        self.vehicle = vehicle
        self.system_id = system_id
        self.component_id = component_id
        self.enc = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)  # message factory
        self.intervals_ns: dict[int, int] = {mid: int(1e9 / hz) for mid, hz in DEFAULT_RATES_HZ.items()}
        self._next_due_ns: dict[int, int] = {}
        self._builders: dict[int, Callable[[], Message]] = {
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
        self._handlers: dict[str, Callable[[Message], list[Message]]] = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target,
            "SET_MODE": self._on_set_mode,
            "TIMESYNC": self._on_timesync,
            "ODOMETRY": self._on_vision,
            "VISION_POSITION_ESTIMATE": self._on_vision,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_COUNT": self._on_mission_upload,
            "MISSION_CLEAR_ALL": self._on_mission_upload,
            "FILE_TRANSFER_PROTOCOL": self._on_ftp,
            "HEARTBEAT": lambda m: [],
        }
        self._commands: dict[int, Callable[[list[float], Message], tuple[Ack, list[Message]]]] = {
            M.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            M.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            M.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            M.MAV_CMD_NAV_LAND: lambda p, m: (self.commander.set_mode(self.now_s, "LAND"), []),
            M.MAV_CMD_NAV_RETURN_TO_LAUNCH: lambda p, m: (self.commander.set_mode(self.now_s, "RTL"), []),
            M.MAV_CMD_DO_FLIGHTTERMINATION: self._cmd_flight_termination,
            M.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            M.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            M.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_request_capabilities,
            M.MAV_CMD_GET_HOME_POSITION: lambda p, m: (Ack(ACCEPTED), [self.home_position()]),
            M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: self._cmd_reboot,
        }
        self._param_names = list(self.vehicle.params.declared)
        self.rx_types: Counter[str] = Counter()
        self.counters = Counter({k: 0 for k in (
            "commands", "commands_unsupported", "commands_refused", "setpoints", "setpoints_rejected",
            "setpoints_nonfinite", "vision_odometry", "vision_position", "vision_rejected_frame", "timesync", "params_sent",
            "handler_errors", "ignored", "ignored_while_rebooting")})
        self.setpoint_max_speed_mps = 0.0   # fastest velocity setpoint received (truth of what the FC got)
        self._reboots_seen = vehicle.reboots
        self._silent_until_ns = -1
        self.vision_error_m: float | None = None  # last vision position vs truth (eval aid)
        self._failsafes_seen = 0
        self._last_error_log_s = 0.0

    # ------------------------------------------------------------------ plumbing

    @property
    def commander(self):
        return self.vehicle.commander

    @property
    def now_s(self) -> float:
        return self.vehicle.time_s

    @property
    def time_boot_ms(self) -> int:
        return (self.vehicle.time_since_boot_ns // 1_000_000) & 0xFFFFFFFF

    @property
    def time_boot_us(self) -> int:
        return self.vehicle.time_since_boot_ns // 1000

    @property
    def rebooting(self) -> bool:
        """After a reboot the autopilot is silent for SIM_REBOOT_T: it neither sends nor listens."""
        if self.vehicle.reboots != self._reboots_seen:  # rebooted (by command or directly)
            self._reboots_seen = self.vehicle.reboots
            self._silent_until_ns = self.vehicle.time_ns + int(self.vehicle.params.SIM_REBOOT_T * 1e9)
            self.intervals_ns = {mid: int(1e9 / hz) for mid, hz in DEFAULT_RATES_HZ.items()}
            self._next_due_ns.clear()
            self._failsafes_seen = 0
        return self.vehicle.time_ns < self._silent_until_ns

    def _for_us(self, m: Message) -> bool:
        ts, tc = getattr(m, "target_system", 0), getattr(m, "target_component", 0)
        return ts in (0, self.system_id) and tc in (0, self.component_id)

    def handle(self, m: Message) -> list[Message]:
        """Process one received message; returns the replies. Never raises."""
        mtype = m.get_type()
        self.rx_types[mtype] += 1
        if self.rebooting:
            self.counters["ignored_while_rebooting"] += 1
            return []
        handler = self._handlers.get(mtype)
        if handler is None:
            self.counters["ignored"] += 1
            return []
        try:
            return handler(m)
        except Exception as e:  # a malformed but CRC-valid message must not stop the vehicle
            self.counters["handler_errors"] += 1
            if time.monotonic() - self._last_error_log_s > 1.0:
                self._last_error_log_s = time.monotonic()
                log.warning("dropped %s: %s: %s", mtype, type(e).__name__, e)
            return []

    def tick(self) -> list[Message]:
        """Telemetry due now (sim time), plus a STATUSTEXT when a failsafe fired."""
        if self.rebooting:
            return []
        now = self.vehicle.time_ns
        out = []
        for mid, interval in self.intervals_ns.items():
            if interval <= 0:
                continue
            due = self._next_due_ns.get(mid, now)
            if now >= due:
                out.append(self._builders[mid]())
                due += interval
                self._next_due_ns[mid] = due if due > now else now + interval
        if self.commander.counters["failsafes"] != self._failsafes_seen:
            self._failsafes_seen = self.commander.counters["failsafes"]
            out.append(self.statustext(M.MAV_SEVERITY_CRITICAL, f"Failsafe: {self.commander.failsafe_reason}"))
        return out

    # ------------------------------------------------------------------ commands

    def _on_command_long(self, m) -> list[Message]:
        params = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]
        return self._command(m, m.command, params)

    def _on_command_int(self, m) -> list[Message]:
        # x/y are lat/lon in degE7 for global frames; z is altitude like param7.
        params = [m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z]
        return self._command(m, m.command, params)

    def _command(self, m, command: int, params: list[float]) -> list[Message]:
        if not self._for_us(m):
            return []
        self.counters["commands"] += 1
        handler = self._commands.get(command)
        if handler is None:
            self.counters["commands_unsupported"] += 1
            return [self._ack(m, command, Ack(M.MAV_RESULT_UNSUPPORTED))]
        ack, extra = handler(params, m)
        out = [self._ack(m, command, ack)]
        if not ack.ok:
            self.counters["commands_refused"] += 1
            if ack.reason:
                out.append(self.statustext(M.MAV_SEVERITY_WARNING, ack.reason))
        return out + extra

    def _ack(self, m, command: int, ack: Ack) -> Message:
        return self.enc.command_ack_encode(command, ack.result, 0, 0, m.get_srcSystem(), m.get_srcComponent())

    def _cmd_arm_disarm(self, p, m):
        force = round(p[1]) == FORCE_MAGIC
        if p[0] >= 0.5:
            return self.commander.arm(self.now_s, force=force), []
        return self.commander.disarm(self.now_s, force=force), []

    def _set_custom_mode(self, base_mode: int, custom_mode: int) -> Ack:
        if not base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return Ack(M.MAV_RESULT_UNSUPPORTED, "only custom (PX4) modes are supported")
        name = px4.decode(custom_mode)
        if name.startswith("PX4("):
            return Ack(DENIED, f"unknown PX4 mode {name}")
        return self.commander.set_mode(self.now_s, name)

    def _cmd_set_mode(self, p, m):
        if not all(math.isfinite(x) for x in p[:3]):
            return Ack(DENIED, "DO_SET_MODE with NaN parameters"), []
        return self._set_custom_mode(int(p[0]), px4.pack(int(p[1]), int(p[2]))), []

    def _on_set_mode(self, m) -> list[Message]:
        """Legacy SET_MODE message: PX4 answers it with a COMMAND_ACK for DO_SET_MODE."""
        if m.target_system not in (0, self.system_id):
            return []
        ack = self._set_custom_mode(m.base_mode, m.custom_mode)
        return [self._ack(m, M.MAV_CMD_DO_SET_MODE, ack)]

    def _cmd_takeoff(self, p, m):
        # PX4 semantics: param7 is the altitude AMSL (NaN: MIS_TAKEOFF_ALT), param4 yaw in degrees.
        home_alt = self.vehicle.params.SIM_HOME_ALT
        altitude = p[6] - home_alt if math.isfinite(p[6]) else math.nan
        yaw = frames.yaw_ned_to_enu(math.radians(p[3])) if math.isfinite(p[3]) else math.nan
        if math.isfinite(altitude) and altitude <= 0.0:
            return Ack(DENIED, f"takeoff altitude {p[6]:.1f} m AMSL is not above home {home_alt:.1f} m"), []
        return self.commander.takeoff(self.now_s, altitude, yaw), []

    def _cmd_flight_termination(self, p, m):
        if p[0] >= 0.5:
            return self.commander.terminate(self.now_s), []
        return Ack(ACCEPTED), []

    def _cmd_request_message(self, p, m):
        builder = self._builders.get(int(p[0])) if math.isfinite(p[0]) else None
        if builder is None:
            return Ack(DENIED, f"message {p[0]:.0f} not available"), []
        return Ack(ACCEPTED), [builder()]

    def _cmd_request_capabilities(self, p, m):
        return Ack(ACCEPTED), ([self.autopilot_version()] if p[0] >= 0.5 else [])

    def _cmd_set_message_interval(self, p, m):
        mid = int(p[0]) if math.isfinite(p[0]) else -1
        if mid not in self._builders or mid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return Ack(DENIED, f"cannot stream message {mid}"), []
        interval_us = p[1]
        if interval_us == 0:  # default rate
            hz = DEFAULT_RATES_HZ.get(mid, 0.0)
            self.intervals_ns[mid] = int(1e9 / hz) if hz > 0 else -1
        elif interval_us < 0:  # disable
            self.intervals_ns[mid] = -1
        else:
            self.intervals_ns[mid] = int(interval_us * 1000)
            self._next_due_ns.pop(mid, None)
        return Ack(ACCEPTED), []

    def _cmd_get_message_interval(self, p, m):
        mid = int(p[0]) if math.isfinite(p[0]) else -1
        if mid not in self._builders:
            return Ack(DENIED), []
        interval_ns = self.intervals_ns.get(mid, -1)
        interval_us = interval_ns // 1000 if interval_ns > 0 else -1
        return Ack(ACCEPTED), [self.enc.message_interval_encode(mid, interval_us)]

    def _cmd_reboot(self, p, m):
        if round(p[0]) != 1:
            return Ack(ACCEPTED), []  # companion / other components: nothing to do here
        if self.commander.armed:
            return Ack(DENIED, "reboot denied: armed"), []
        self.vehicle.reboot()
        return Ack(ACCEPTED), []

    # ------------------------------------------------------------------ setpoints, vision, time

    def _on_set_position_target(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        sp = setpoint_from_mavlink(m)
        if sp is None:
            self.counters["setpoints_rejected"] += 1
            return []
        self.counters["setpoints"] += 1
        self._record_setpoint_truth(m)
        self.commander.on_offboard_setpoint(self.now_s, sp)
        return []

    def _record_setpoint_truth(self, m) -> None:
        """What reached the FC, for tests of the sender: used (not type_mask-ignored) fields that
        are not finite (acceleration included), and the fastest velocity setpoint."""
        tm = m.type_mask
        used = [v for v, bit in zip((m.x, m.y, m.z, m.vx, m.vy, m.vz, m.afx, m.afy, m.afz),
                                    _IGNORE_POS + _IGNORE_VEL + _IGNORE_ACC) if not tm & bit]
        if not tm & M.POSITION_TARGET_TYPEMASK_YAW_IGNORE:
            used.append(m.yaw)
        if not tm & M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE:
            used.append(m.yaw_rate)
        if not all(math.isfinite(v) for v in used):
            self.counters["setpoints_nonfinite"] += 1
        vel = [0.0 if tm & bit or not math.isfinite(v) else v for v, bit in zip((m.vx, m.vy, m.vz), _IGNORE_VEL)]
        self.setpoint_max_speed_mps = max(self.setpoint_max_speed_mps, math.sqrt(sum(v * v for v in vel)))

    def _on_vision(self, m) -> list[Message]:
        """Vision from the companion (fmu injects the VIO): count it, measure it against the
        truth (an end-to-end check) and, GPS-denied, fuse it (estimator.py). NED/FRD -> ENU/FLU
        here, through frames.py."""
        odom = m.get_type() == "ODOMETRY"
        self.counters["vision_odometry" if odom else "vision_position"] += 1
        pos_enu = frames.ned_to_enu(np.array([m.x, m.y, m.z], dtype=float))
        if np.all(np.isfinite(pos_enu)):
            self.vision_error_m = float(np.linalg.norm(pos_enu - self.vehicle.state.position_enu_m))
        if odom:
            if m.frame_id not in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_FRD) or m.child_frame_id not in (
                    M.MAV_FRAME_BODY_FRD,):
                self.counters["vision_rejected_frame"] += 1
                return []
            q = frames.q_ned_frd_to_enu_flu(np.array(m.q, dtype=float))
            vel = frames.frd_to_flu(np.array([m.vx, m.vy, m.vz], dtype=float))
            pos_var = vel_var = None
            if math.isfinite(m.pose_covariance[0]):
                pos_var = np.diag(frames.cov6_ned_frd_to_enu_flu(frames.urt21_to_cov6(m.pose_covariance)))[:3]
            if math.isfinite(m.velocity_covariance[0]):
                vel_var = np.diag(frames.cov6_frd_to_flu(frames.urt21_to_cov6(m.velocity_covariance)))[:3]
            self.vehicle.estimator.on_vision(self.vehicle.time_ns, int(m.time_usec) * 1000, pos_enu, q, vel,
                                             pos_var, vel_var, m.reset_counter)
        else:
            q = frames.q_ned_frd_to_enu_flu(frames.quat_from_euler(m.roll, m.pitch, m.yaw))
            self.vehicle.estimator.on_vision(self.vehicle.time_ns, int(m.usec) * 1000, pos_enu, q)
        return []

    def _on_timesync(self, m) -> list[Message]:
        if m.tc1 != 0:
            return []  # a reply to someone else's request
        self.counters["timesync"] += 1
        return [self.enc.timesync_encode(self.vehicle.time_since_boot_ns, m.ts1)]

    # ------------------------------------------------------------------ parameters

    def param_value(self, index: int) -> Message:
        name = self._param_names[index]
        value = self.vehicle.params[name]
        if isinstance(value, float):
            wire, ptype = value, M.MAV_PARAM_TYPE_REAL32
        else:  # int and bool travel bytewise in the float field, as PX4 sends them
            wire, ptype = int_to_float_bits(int(value)), M.MAV_PARAM_TYPE_INT32
        self.counters["params_sent"] += 1
        return self.enc.param_value_encode(name.encode(), wire, ptype, len(self._param_names), index)

    def _on_param_request_list(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        return [self.param_value(i) for i in range(len(self._param_names))]

    def _param_index(self, param_id: str, index: int) -> int | None:
        if index >= 0:
            return index if index < len(self._param_names) else None
        return self._param_names.index(param_id) if param_id in self._param_names else None

    def _on_param_request_read(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        i = self._param_index(m.param_id, m.param_index)
        return [] if i is None else [self.param_value(i)]

    def _on_param_set(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        i = self._param_index(m.param_id, -1)
        if i is None:
            return [self.statustext(M.MAV_SEVERITY_WARNING, f"unknown parameter {m.param_id}")]
        name = self._param_names[i]
        decl = self.vehicle.params.declared[name]
        out = []
        if decl.type is float:
            candidates = [m.param_value]
        else:  # bytewise (PX4) first, then a C cast (ArduPilot-style senders)
            raw = [float_bits_to_int(m.param_value)] if m.param_type != M.MAV_PARAM_TYPE_REAL32 else []
            candidates = raw + ([int(m.param_value)] if float(m.param_value).is_integer() else [])
            candidates = [bool(c) if decl.type is bool and c in (0, 1) else c for c in candidates]
        for value in candidates:
            try:
                self.vehicle.params.set(name, value)
                break
            except ParamError as e:
                error = str(e)
        else:
            out.append(self.statustext(M.MAV_SEVERITY_WARNING, error if candidates else f"{name}: bad value"))
        return [self.param_value(i)] + out

    # ------------------------------------------------------------------ missions, FTP (refused)

    def _on_mission_request_list(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        return [self.enc.mission_count_encode(m.get_srcSystem(), m.get_srcComponent(), 0, m.mission_type)]

    def _on_mission_upload(self, m) -> list[Message]:
        if not self._for_us(m):
            return []
        result = M.MAV_MISSION_ACCEPTED if m.get_type() == "MISSION_CLEAR_ALL" else M.MAV_MISSION_UNSUPPORTED
        return [self.enc.mission_ack_encode(m.get_srcSystem(), m.get_srcComponent(), result, m.mission_type)]

    def _on_ftp(self, m) -> list[Message]:
        """NAK every MAVLink FTP request so ground stations fall back to the parameter protocol
        at once instead of timing out (MAVProxy waits ~11 s otherwise)."""
        if m.target_system not in (0, self.system_id):
            return []
        return [ftp.nak(m, ftp.ERR_UNKNOWN_COMMAND)]

    # ------------------------------------------------------------------ telemetry builders

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

    def stream_rates_hz(self) -> dict[str, float]:
        """Current telemetry rates by message name (0: off), in sim time."""
        return {M.mavlink_map[mid].msgname: (1e9 / iv if iv > 0 else 0.0) for mid, iv in self.intervals_ns.items()}

    def diagnostics(self) -> dict:
        """Flat counters (per-type receive counts are in `rx_types`)."""
        est = self.vehicle.estimator
        return {**self.counters, **est.counters, "vision_error_m": self.vision_error_m,
                "gps_denied": est.gps_denied, "position_valid": est.valid(self.vehicle.time_ns),
                "estimate_error_m": round(float(np.linalg.norm(self.vehicle.estimate.position_enu_m
                                                             - self.vehicle.state.position_enu_m)), 3), "last_reason": self.commander.last_reason,
                "setpoint_max_speed_mps": round(self.setpoint_max_speed_mps, 3), "time_boot_ms": self.time_boot_ms,
                "rebooting": self.vehicle.time_ns < self._silent_until_ns}

