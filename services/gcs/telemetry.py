"""Telemetry to the ground station from the stack's state (no Zenoh): message builders and the
per-message interval scheduler (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE).

Everything arrives ENU/FLU (state/vehicle) and leaves NED/FRD through services/mavlink/frames.py;
geodetic positions are the local position projected about home (services/lib/geo.py): the
flight controller's home once fmu reports it, else gcs's home parameters (see home.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import (
    BatteryState, EstimatorStatus, GpsPosition, LandedState, MissionStatus, SafetyStatus, VehicleState,
)
from aeroperception.services.mavlink import frames, px4

from .messages import MissionCurrent
from .home import Home
from .mission_progress import Progress

# What we really support. Not SET_POSITION_TARGET_LOCAL_NED: offboard setpoints from a
# ground station would bypass the mission manager and the planner; such messages are counted as
# ignored (diagnostics `ignored[SET_POSITION_TARGET_LOCAL_NED]`).
CAPABILITIES = (M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)
FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255   # reported as PX4 v1.15.0 (official)
SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
           | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS
           | M.MAV_SYS_STATUS_SENSOR_BATTERY)

FENCE = M.MAV_SYS_STATUS_GEOFENCE
SAFETY_STALE_S = 3.0      # safety/status (1 Hz) older than this: the geofence is unknown, not reported
# fmu/out/vehicle_gps_position and fmu/out/estimator_status (1 Hz) older than this are not reported:
# GPS_RAW_INT says NO_GPS, ESTIMATOR_STATUS is not sent (we never invent the FC's GPS or estimator)
FC_STATUS_STALE_S = 3.0
UINT16_UNKNOWN = 0xFFFF

ID = {name: getattr(M, f"MAVLINK_MSG_ID_{name}") for name in (
    "HEARTBEAT", "SYS_STATUS", "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT", "GPS_RAW_INT",
    "HOME_POSITION", "EXTENDED_SYS_STATE", "MISSION_CURRENT", "BATTERY_STATUS", "AUTOPILOT_VERSION",
    "ATTITUDE_QUATERNION", "ESTIMATOR_STATUS",
)}
# The default set, sent every telemetry period (telemetry_period_s, 900 ms by default).
DEFAULT_STREAM = ["HEARTBEAT", "SYS_STATUS", "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT",
                  "GPS_RAW_INT", "HOME_POSITION", "EXTENDED_SYS_STATE", "MISSION_CURRENT", "BATTERY_STATUS",
                  "ESTIMATOR_STATUS"]


@dataclass
class TelemetryState:
    """The latest of everything telemetry is made from."""

    home: Home
    vehicle: VehicleState | None = None
    battery: BatteryState | None = None
    mission: MissionStatus | None = None
    mission_seq: int = 0            # MISSION_CURRENT.seq (item index)
    mission_total: int = 0
    mission_id: int = 0             # MISSION_CURRENT.mission_id: the plan's id (mission_items.plan_id), 0 = none
    progress: Progress | None = None  # the mission protocol's progress (current item, mission_state)
    safety: SafetyStatus | None = None
    safety_rx_s: float = 0.0        # monotonic time safety/status last arrived
    gps: GpsPosition | None = None  # the FC's GPS receiver (fmu/out/vehicle_gps_position)
    gps_rx_s: float = -math.inf
    estimator: EstimatorStatus | None = None  # the FC's estimator flags (fmu/out/estimator_status)
    estimator_rx_s: float = -math.inf
    companion: bool = False         # vehicle profile: we are the FC's onboard computer (heartbeat only)
    boot_s: float = field(default_factory=time.monotonic)

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.boot_s) * 1000) & 0xFFFFFFFF

    # ------------------------------------------------------------ builders

    def heartbeat(self):
        v = self.vehicle
        if self.companion:
            status = M.MAV_STATE_ACTIVE if v is not None and v.connected else M.MAV_STATE_STANDBY
            return M.MAVLink_heartbeat_message(M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, status, 3)
        armed = bool(v and v.armed)
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
        mode = (v.flight_mode if v else "") or "HOLD"
        try:
            custom = px4.encode(mode)
        except KeyError:
            custom = px4.encode("HOLD")
        main, _ = px4.unpack(custom)
        if main in (px4.PX4_MAIN["AUTO"], px4.PX4_MAIN["OFFBOARD"], px4.PX4_MAIN["POSCTL"]):
            base |= M.MAV_MODE_FLAG_GUIDED_ENABLED
        if main == px4.PX4_MAIN["AUTO"]:
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED
        if armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        status = M.MAV_STATE_ACTIVE if armed else M.MAV_STATE_STANDBY
        if v is None or not v.connected:
            status = M.MAV_STATE_UNINIT if v is None else M.MAV_STATE_CRITICAL
        return M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base, custom, status, 3)

    def _battery(self) -> tuple[float | None, float | None, float | None]:
        b, v = self.battery, self.vehicle
        volt = b.voltage_v if b is not None else (v.battery_voltage_v if v else None)
        cur = b.current_a if b is not None else None
        rem = b.remaining_fraction if b is not None else (v.battery_remaining if v else None)
        return volt, cur, rem

    def fence_bits(self, now_s: float | None = None) -> tuple[int, int, int]:
        """SYS_STATUS geofence (present, enabled, healthy) from safety/status: not
        present without a fresh safety/status; enabled when safety has a geofence (a distance to
        it); healthy unless safety reports a violation."""
        now = time.monotonic() if now_s is None else now_s
        s = self.safety
        if s is None or now - self.safety_rx_s > SAFETY_STALE_S:
            return 0, 0, 0
        enabled = FENCE if s.distance_to_geofence_m is not None else 0
        healthy = FENCE if s.geofence_status != SafetyStatus.GEOFENCE_VIOLATION else 0
        return FENCE, enabled, healthy

    def sys_status(self):
        volt, cur, rem = self._battery()
        healthy = SENSORS if self.vehicle is not None and self.vehicle.connected else 0
        present, enabled, fence_ok = self.fence_bits()
        return M.MAVLink_sys_status_message(
            SENSORS | present, SENSORS | enabled, healthy | fence_ok, 500,
            int(volt * 1000) if volt else 0xFFFF, int(cur * 100) if cur is not None else -1,
            int(round(rem * 100)) if rem is not None else -1, 0, 0, 0, 0, 0, 0)

    def battery_status(self):
        volt, cur, rem = self._battery()
        cells = [0xFFFF] * 10
        if volt:
            cells[0] = min(0xFFFE, int(volt * 1000))
        temp = self.battery.temperature_c if self.battery is not None and self.battery.temperature_c is not None else None
        return M.MAVLink_battery_status_message(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO,
            int(temp * 100) if temp is not None else 0x7FFF, cells,
            int(cur * 100) if cur is not None else -1, -1, -1,
            int(round(rem * 100)) if rem is not None else -1)

    def local_position_ned(self):
        v = self.vehicle or VehicleState()
        p = frames.enu_to_ned(v.position_m.to_array())
        vel = frames.enu_to_ned(v.velocity_mps.to_array())
        return M.MAVLink_local_position_ned_message(self.boot_ms(), *map(float, p), *map(float, vel))

    def attitude(self):
        v = self.vehicle or VehicleState()
        q = frames.q_enu_flu_to_ned_frd(v.orientation.to_array() if hasattr(v.orientation, "to_array")
                                        else [v.orientation.w, v.orientation.x, v.orientation.y, v.orientation.z])
        roll, pitch, yaw = (float(a) for a in frames.quat_to_euler(q))
        rates = frames.flu_to_frd(v.angular_velocity_radps.to_array())
        return M.MAVLink_attitude_message(self.boot_ms(), roll, pitch, yaw, *map(float, rates))

    def _geo(self):
        v = self.vehicle or VehicleState()
        lat, lon, rel = self.home.to_geodetic(v.position_m.x, v.position_m.y, v.position_m.z)
        return v, lat, lon, rel

    def global_position_int(self):
        v, lat, lon, rel = self._geo()
        vel = frames.enu_to_ned(v.velocity_mps.to_array())
        hdg = math.degrees(frames.yaw_enu_to_ned(v.yaw_rad)) % 360.0
        return M.MAVLink_global_position_int_message(
            self.boot_ms(), int(round(lat * 1e7)), int(round(lon * 1e7)),
            int(round((self.home.alt_m + rel) * 1000)), int(round(rel * 1000)),
            *(int(round(c * 100)) for c in vel), int(round(hdg * 100)) % 36000)

    def fresh_gps(self, now_s: float | None = None) -> GpsPosition | None:
        now = time.monotonic() if now_s is None else now_s
        return self.gps if now - self.gps_rx_s <= FC_STATUS_STALE_S else None

    def gps_raw_int(self):
        """The FC's GPS receiver as fmu reports it: NO_GPS while there is no (fresh) report, NO_FIX
        with no position when the receiver has no fix. Never the fused position dressed as a fix."""
        g = self.fresh_gps() or GpsPosition()

        def scaled(value: float | None, scale: float, top: int = UINT16_UNKNOWN - 1) -> int:
            return UINT16_UNKNOWN if value is None else min(top, max(0, int(round(value * scale))))

        def mm_or_0(value_m: float | None) -> int:   # h_acc / v_acc (uint32 mm): 0 = not known
            return 0 if value_m is None else min(0xFFFFFFFF, max(1, int(round(value_m * 1000))))

        cog = None if g.course_rad is None else math.degrees(frames.yaw_enu_to_ned(g.course_rad)) % 360.0
        return M.MAVLink_gps_raw_int_message(
            int(time.time() * 1e6), g.fix_type,
            int(round((g.latitude_deg or 0.0) * 1e7)), int(round((g.longitude_deg or 0.0) * 1e7)),
            int(round((g.altitude_amsl_m or 0.0) * 1000)), scaled(g.hdop, 100), scaled(g.vdop, 100),
            scaled(g.ground_speed_mps, 100), scaled(cog, 100, 35999),
            0xFF if g.satellites_visible is None else min(254, g.satellites_visible), 0,
            mm_or_0(g.horizontal_accuracy_m), mm_or_0(g.vertical_accuracy_m), 0, 0, 0)

    def estimator_status(self):
        """The FC's ESTIMATOR_STATUS as fmu reports it (flags: POS_HORIZ_REL without POS_HORIZ_ABS =
        position from vision alone); None (not sent) without a fresh report."""
        now = time.monotonic()
        e = self.estimator if now - self.estimator_rx_s <= FC_STATUS_STALE_S else None
        if e is None:
            return None
        nan = float("nan")

        def f(value: float | None) -> float:
            return nan if value is None else value

        return M.MAVLink_estimator_status_message(
            int(time.time() * 1e6), e.flags & UINT16_UNKNOWN, f(e.velocity_test_ratio),
            f(e.position_horizontal_test_ratio), f(e.position_vertical_test_ratio), f(e.magnetometer_test_ratio),
            f(e.height_above_ground_test_ratio), f(e.airspeed_test_ratio), f(e.position_horizontal_accuracy_m),
            f(e.position_vertical_accuracy_m))

    def home_position(self):
        h = self.home
        x, y, z = (float(c) for c in frames.enu_to_ned(h.local_m))   # home in the local NED frame
        return M.MAVLink_home_position_message(
            int(round(h.lat_deg * 1e7)), int(round(h.lon_deg * 1e7)), int(round(h.alt_m * 1000)),
            x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def extended_sys_state(self):
        landed = self.vehicle.landed_state if self.vehicle else LandedState.UNDEFINED
        return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, landed)

    def mission_current(self):
        pr = self.progress
        if pr is not None and self.mission_total and pr.total == self.mission_total:
            return MissionCurrent(pr.current, pr.total, pr.state, pr.mode, self.mission_id)
        st = self.mission
        state = M.MISSION_STATE_NO_MISSION if self.mission_total == 0 else M.MISSION_STATE_NOT_STARTED
        if st is not None and self.mission_total:
            if st.state == "EXECUTING":
                state = M.MISSION_STATE_ACTIVE
            elif st.state == "HOLDING" and st.active_waypoint >= 0:
                state = M.MISSION_STATE_PAUSED
        return MissionCurrent(self.mission_seq, self.mission_total, state, 0,
                              self.mission_id if self.mission_total else 0)

    def autopilot_version(self):
        return M.MAVLink_autopilot_version_message(
            CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x4145524F)

    def build(self, msg_id: int):
        """The message with this id, or None if we cannot produce it."""
        fn = {
            ID["HEARTBEAT"]: self.heartbeat, ID["SYS_STATUS"]: self.sys_status,
            ID["LOCAL_POSITION_NED"]: self.local_position_ned, ID["ATTITUDE"]: self.attitude,
            ID["GLOBAL_POSITION_INT"]: self.global_position_int, ID["GPS_RAW_INT"]: self.gps_raw_int,
            ID["HOME_POSITION"]: self.home_position, ID["EXTENDED_SYS_STATE"]: self.extended_sys_state,
            ID["MISSION_CURRENT"]: self.mission_current, ID["BATTERY_STATUS"]: self.battery_status,
            ID["AUTOPILOT_VERSION"]: self.autopilot_version, ID["ESTIMATOR_STATUS"]: self.estimator_status,
        }.get(msg_id)
        return fn() if fn else None


class Scheduler:
    """Per-message periods: the default set at `default_period_s`, changed by SET_MESSAGE_INTERVAL."""

    def __init__(self, default_period_s: float, build: Callable[[int], object]):
        self.default_period_s = default_period_s
        self.build = build
        self.periods: dict[int, float] = {ID[n]: default_period_s for n in DEFAULT_STREAM}
        self.last: dict[int, float] = {}

    def set_interval(self, msg_id: int, interval_us: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL semantics: -1 disable, 0 default, >0 microseconds."""
        if self.build(msg_id) is None:
            return False
        if interval_us < 0:
            self.periods.pop(msg_id, None)
        elif interval_us == 0:
            if any(ID[n] == msg_id for n in DEFAULT_STREAM):
                self.periods[msg_id] = self.default_period_s
            else:
                self.periods.pop(msg_id, None)
        else:
            self.periods[msg_id] = max(0.01, interval_us / 1e6)
        return True

    def due(self, now_s: float) -> list:
        out = []
        for mid, period in list(self.periods.items()):
            if now_s - self.last.get(mid, -1e9) >= period - 1e-3:
                msg = self.build(mid)
                if msg is not None:
                    out.append(msg)
                self.last[mid] = now_s
        return out
