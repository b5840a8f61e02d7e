"""The vehicle's MAVLink receiver, like PX4's mavlink_receiver: one handler per incoming message
type (commands, offboard setpoints, vision, time sync, parameters, the refused mission and FTP
protocols) turning it into commander / estimator calls and the replies it owes.

No sockets here (the runner moves the messages). NED/FRD -> ENU/FLU only through
services/mavlink/frames.py.
"""
from __future__ import annotations

import math
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
from .mavlink_streams import OnVehicle, TelemetryStreams

M = mavlink
Message = mavlink.MAVLink_message

FORCE_MAGIC = 21196  # COMPONENT_ARM_DISARM param2: skip checks (PX4, ArduPilot)

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


class MavlinkReceiver(OnVehicle):
    """Handles what arrives for this vehicle; `handlers` maps a message type to its handler."""

    def __init__(self, vehicle: SimVehicle, streams: TelemetryStreams, system_id: int, component_id: int):
        self.vehicle = vehicle
        self.streams = streams
        self.enc = streams.enc
        self.system_id = system_id
        self.component_id = component_id
        self.handlers: dict[str, Callable[[Message], list[Message]]] = {
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
            M.MAV_CMD_GET_HOME_POSITION: lambda p, m: (Ack(ACCEPTED), [self.streams.home_position()]),
            M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: self._cmd_reboot,
        }
        self._param_names = list(self.vehicle.params.declared)
        self.counters = Counter({k: 0 for k in (
            "commands", "commands_unsupported", "commands_refused", "setpoints", "setpoints_rejected",
            "setpoints_nonfinite", "vision_odometry", "vision_position", "vision_rejected_frame", "timesync", "params_sent",
            "handler_errors", "ignored", "ignored_while_rebooting")})
        self.setpoint_max_speed_mps = 0.0   # fastest velocity setpoint received (truth of what the FC got)
        self.vision_error_m: float | None = None  # last vision position vs truth (eval aid)

    def _for_us(self, m: Message) -> bool:
        ts, tc = getattr(m, "target_system", 0), getattr(m, "target_component", 0)
        return ts in (0, self.system_id) and tc in (0, self.component_id)

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
                out.append(self.streams.statustext(M.MAV_SEVERITY_WARNING, ack.reason))
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
        builder = self.streams.builders.get(int(p[0])) if math.isfinite(p[0]) else None
        if builder is None:
            return Ack(DENIED, f"message {p[0]:.0f} not available"), []
        return Ack(ACCEPTED), [builder()]

    def _cmd_request_capabilities(self, p, m):
        return Ack(ACCEPTED), ([self.streams.autopilot_version()] if p[0] >= 0.5 else [])

    def _cmd_set_message_interval(self, p, m):
        mid = int(p[0]) if math.isfinite(p[0]) else -1
        if not self.streams.set_interval(mid, p[1]):
            return Ack(DENIED, f"cannot stream message {mid}"), []
        return Ack(ACCEPTED), []

    def _cmd_get_message_interval(self, p, m):
        mid = int(p[0]) if math.isfinite(p[0]) else -1
        interval_us = self.streams.interval_us(mid)
        if interval_us is None:
            return Ack(DENIED), []
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
            return [self.streams.statustext(M.MAV_SEVERITY_WARNING, f"unknown parameter {m.param_id}")]
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
            out.append(self.streams.statustext(M.MAV_SEVERITY_WARNING, error if candidates else f"{name}: bad value"))
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
