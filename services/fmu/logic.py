"""fmu logic, free of Zenoh and sockets: MAVLink messages in, ENU schemas out, and back.

Every NED/FRD <-> ENU/FLU conversion goes through services/mavlink/frames; mode names through
services/mavlink/px4 (PX4 or ArduPilot maps chosen from the heartbeat's autopilot field).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import msgspec
import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import (
    Attitude, BatteryState, Header, HomePosition, Imu, LandedState, LocalPosition, Odometry, Quaternion,
    TrajectorySetpoint, Vector3, VehicleState, VehicleStatus,
)
from aeroperception.services.mavlink import frames
from aeroperception.services.mavlink.px4 import Autopilot

from .offboard import hold_setpoint

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (1 = ignore)
IGNORE_POS = 0b0000_0000_0111
IGNORE_VEL = 0b0000_0011_1000
IGNORE_ACC = 0b0001_1100_0000
IGNORE_YAW = 0b0100_0000_0000
IGNORE_YAW_RATE = 0b1000_0000_0000

MAV_LANDED = {
    mavlink.MAV_LANDED_STATE_UNDEFINED: LandedState.UNDEFINED,
    mavlink.MAV_LANDED_STATE_ON_GROUND: LandedState.ON_GROUND,
    mavlink.MAV_LANDED_STATE_IN_AIR: LandedState.IN_AIR,
    mavlink.MAV_LANDED_STATE_TAKEOFF: LandedState.TAKEOFF,
    mavlink.MAV_LANDED_STATE_LANDING: LandedState.LANDING,
}


@dataclass
class Telemetry:
    """Latest flight-controller state, assembled from MAVLink, in ENU/FLU."""

    autopilot: Autopilot = field(default_factory=lambda: Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_PX4))
    position_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q_enu_flu: np.ndarray = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    rates_flu_radps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
    have_position: bool = False
    armed: bool = False
    custom_mode: int = 0
    base_mode: int = 0
    flight_mode: str = ""
    system_status: int = 0
    landed_state: int = LandedState.UNDEFINED
    battery_remaining: float | None = None
    battery_voltage_v: float | None = None
    battery_current_a: float | None = None
    last_rx_s: float = 0.0
    last_heartbeat_s: float = 0.0
    system_id: int = 1
    home: HomePosition | None = None      # the FC's home (HOME_POSITION), None until it sends one
    last_status: VehicleStatus | None = None  # last published (header cleared), see status_to_publish

    def on_heartbeat(self, m) -> VehicleStatus:
        if m.autopilot != self.autopilot.mav_autopilot:
            self.autopilot = Autopilot.for_heartbeat(m.autopilot)
        self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self.base_mode, self.custom_mode = m.base_mode, m.custom_mode
        self.flight_mode = self.autopilot.mode_name(m.custom_mode)
        self.system_status = m.system_status
        self.last_heartbeat_s = time.monotonic()
        return self.vehicle_status()

    def status_to_publish(self, stamp_ns: int, periodic: bool) -> VehicleStatus | None:
        """The status to publish now: always on the periodic tick (STATUS_RATE_HZ), and from a
        heartbeat only when it changed what was last published (a mode or arming change goes
        out at once without doubling the rate)."""
        st = self.vehicle_status(stamp_ns)
        body = msgspec.structs.replace(st, header=Header())
        if not periodic and body == self.last_status:
            return None
        self.last_status = body
        return st

    def vehicle_status(self, stamp_ns: int = 0) -> VehicleStatus:
        return VehicleStatus(header=Header(stamp_ns=stamp_ns), nav_state=self.flight_mode, custom_mode=self.custom_mode, armed=self.armed,
                             landed_state=self.landed_state,
                             failsafe=self.system_status in (mavlink.MAV_STATE_CRITICAL, mavlink.MAV_STATE_EMERGENCY),
                             system_id=self.system_id, autopilot=self.autopilot.name)

    def on_local_position(self, m, stamp_ns: int) -> LocalPosition:
        self.position_m = frames.ned_to_enu(np.array([m.x, m.y, m.z]))
        self.velocity_mps = frames.ned_to_enu(np.array([m.vx, m.vy, m.vz]))
        self.have_position = True
        return LocalPosition(header=Header(stamp_ns=stamp_ns, frame_id="map"), position_m=Vector3.from_array(self.position_m),
                             velocity_mps=Vector3.from_array(self.velocity_mps), yaw_rad=self.yaw_rad,
                             position_valid=True, velocity_valid=True)

    def on_attitude_quaternion(self, m, stamp_ns: int) -> Attitude:
        self.q_enu_flu = frames.q_ned_frd_to_enu_flu(np.array([m.q1, m.q2, m.q3, m.q4]))
        self.rates_flu_radps = frames.frd_to_flu(np.array([m.rollspeed, m.pitchspeed, m.yawspeed]))
        self.yaw_rad = frames.yaw_from_q(self.q_enu_flu)
        return Attitude(header=Header(stamp_ns=stamp_ns, frame_id="map"), orientation=Quaternion.from_array(self.q_enu_flu),
                        angular_velocity_radps=Vector3.from_array(self.rates_flu_radps))

    def on_home_position(self, m, stamp_ns: int) -> HomePosition | None:
        """HOME_POSITION -> HomePosition (kept as `home`); None (and `home` unchanged) if the FC
        reports no usable home. Returns the new home whether or not it changed."""
        home = home_position_from_mavlink(m, stamp_ns)
        if home is not None:
            self.home = home
        return home

    def on_extended_sys_state(self, m) -> None:
        self.landed_state = MAV_LANDED.get(m.landed_state, LandedState.UNDEFINED)

    def on_sys_status(self, m) -> None:
        if m.battery_remaining >= 0:
            self.battery_remaining = m.battery_remaining / 100.0
        if m.voltage_battery not in (0, 0xFFFF):
            self.battery_voltage_v = m.voltage_battery / 1000.0
        if m.current_battery >= 0:
            self.battery_current_a = m.current_battery / 100.0

    def on_battery_status(self, m, stamp_ns: int) -> BatteryState:
        if m.battery_remaining >= 0:
            self.battery_remaining = m.battery_remaining / 100.0
        cells = [v for v in m.voltages if v != 0xFFFF]
        if cells:
            self.battery_voltage_v = sum(cells) / 1000.0
        if m.current_battery >= 0:
            self.battery_current_a = m.current_battery / 100.0
        return self.battery(stamp_ns, temperature_c=None if m.temperature == 0x7FFF else m.temperature / 100.0,
                            cell_count=len(cells))

    def battery(self, stamp_ns: int, **extra) -> BatteryState:
        kw = {k: v for k, v in dict(voltage_v=self.battery_voltage_v, current_a=self.battery_current_a,
                                    remaining_fraction=self.battery_remaining, **extra).items() if v is not None}
        return BatteryState(header=Header(stamp_ns=stamp_ns), **kw)

    def vehicle_state(self, stamp_ns: int, connected: bool) -> VehicleState:
        roll, pitch, _ = frames.euler_from_q(self.q_enu_flu)
        return VehicleState(
            header=Header(stamp_ns=stamp_ns, frame_id="map"),
            position_m=Vector3.from_array(self.position_m), velocity_mps=Vector3.from_array(self.velocity_mps),
            orientation=Quaternion.from_array(self.q_enu_flu), angular_velocity_radps=Vector3.from_array(self.rates_flu_radps),
            roll_rad=roll, pitch_rad=pitch, yaw_rad=self.yaw_rad,
            estimator_name=f"{self.autopilot.name}-ekf", confidence=1.0 if connected else 0.0,
            flight_mode=self.flight_mode, armed=self.armed, landed_state=self.landed_state,
            battery_remaining=self.battery_remaining, battery_voltage_v=self.battery_voltage_v,
            connected=connected)


def home_position_from_mavlink(m, stamp_ns: int) -> HomePosition | None:
    """HOME_POSITION (lat/lon degE7, altitude mm AMSL, x/y/z local NED of home) -> HomePosition
    (position_m local ENU). None when there is no usable home: latitude/longitude out of range,
    or both exactly 0 (what autopilots send before a home is set). A non-finite local position
    is taken as the local origin."""
    lat, lon, alt = m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1e3
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or (m.latitude == 0 and m.longitude == 0):
        return None
    ned = np.array([m.x, m.y, m.z], dtype=float)
    if not np.all(np.isfinite(ned)):
        ned = np.zeros(3)
    return HomePosition(header=Header(stamp_ns=stamp_ns, frame_id="map"), latitude_deg=lat, longitude_deg=lon,
                        altitude_amsl_m=alt, position_m=Vector3.from_array(frames.ned_to_enu(ned) + 0.0))  # no -0.0


def highres_imu_to_imu(m, stamp_ns: int) -> Imu:
    """HIGHRES_IMU (FRD body) -> Imu (FLU body), specific force incl. gravity as the FC reports it."""
    return Imu(header=Header(stamp_ns=stamp_ns, frame_id="base_link"),
               angular_velocity_radps=Vector3.from_array(frames.frd_to_flu(np.array([m.xgyro, m.ygyro, m.zgyro]))),
               linear_acceleration_mps2=Vector3.from_array(frames.frd_to_flu(np.array([m.xacc, m.yacc, m.zacc]))))


def setpoint_target(sp: TrajectorySetpoint) -> dict:
    """TrajectorySetpoint (ENU) -> SET_POSITION_TARGET_LOCAL_NED fields (NED): every part marked
    valid is sent and its type_mask bits cleared; the others are ignored and sent as finite zeros.
    Acceleration is feed-forward (PX4 adds it to its velocity controller's output; FORCE_SET stays
    clear). Jerk has no field in the message: the Envelope refuses a setpoint that marks it valid."""
    mask = 0
    pos = vel = acc = np.zeros(3)
    if sp.position_valid:
        pos = frames.enu_to_ned(sp.position_m.to_array())
    else:
        mask |= IGNORE_POS
    if sp.velocity_valid:
        vel = frames.enu_to_ned(sp.velocity_mps.to_array())
    else:
        mask |= IGNORE_VEL
    if sp.acceleration_valid:
        acc = frames.enu_to_ned(sp.acceleration_mps2.to_array())
    else:
        mask |= IGNORE_ACC
    yaw = yaw_rate = 0.0
    if sp.yaw_valid and math.isfinite(sp.yaw_rad):
        yaw = frames.yaw_enu_to_ned(sp.yaw_rad)
    else:
        mask |= IGNORE_YAW
    if sp.yaw_rate_valid and math.isfinite(sp.yaw_rate_radps):
        yaw_rate = frames.yaw_rate_enu_to_ned(sp.yaw_rate_radps)
    else:
        mask |= IGNORE_YAW_RATE
    return dict(coordinate_frame=mavlink.MAV_FRAME_LOCAL_NED, type_mask=mask,
                x=float(pos[0]), y=float(pos[1]), z=float(pos[2]),
                vx=float(vel[0]), vy=float(vel[1]), vz=float(vel[2]),
                afx=float(acc[0]), afy=float(acc[1]), afz=float(acc[2]), yaw=float(yaw), yaw_rate=float(yaw_rate))


def hold_target(position_enu_m: np.ndarray, yaw_enu_rad: float) -> dict:
    """Hold here: position + zero velocity (offboard.hold_setpoint) as MAVLink fields."""
    return setpoint_target(hold_setpoint(position_enu_m, yaw_enu_rad))


def odometry_fields(odom: Odometry, time_usec: int) -> dict:
    """Odometry (ENU pose, FLU twist) -> MAVLink ODOMETRY as PX4's EKF2 fuses it (EKF2_EV_CTRL):
    - frame_id LOCAL_FRD: the VIO's odom frame has its origin and yaw where the VIO initialised, not
      North; PX4 takes LOCAL_NED as North-aligned and fuses it as such, but rotates a LOCAL_FRD pose
      onto its own heading (the filtered attitude difference). The pose is the odom frame with its
      axes swapped as for NED (a z-down frame of arbitrary heading) and q rotates body FRD into it.
    - child_frame_id BODY_FRD: velocity in the body frame (EKF2 rotates it with its own attitude).
    - time_usec: the pose's exposure stamp in the clock fmu answers PX4's TIMESYNC in (the node's),
      so PX4 converts it into its own once its time sync has converged.
    - covariances: upper-right triangles (EKF2 reads the diagonals, used with EKF2_EV_NOISE_MD 0);
      NaN first element when the estimator gave none.
    - reset_counter: the estimator's (uint8, wrapping): on a change EKF2 re-aligns to the new pose
      (resets its vision frame and position) instead of rejecting the jump as an innovation outlier.
    - quality: the estimator's 1-100, 0 (MAVLink's "unknown") when it gives none; EKF2 fuses only
      samples at or above EKF2_EV_QMIN."""
    p = frames.enu_to_ned(odom.pose.position.to_array())
    o = odom.pose.orientation
    q = frames.q_enu_flu_to_ned_frd(np.array([o.w, o.x, o.y, o.z]))
    v_body = frames.flu_to_frd(odom.twist.linear.to_array())
    w_body = frames.flu_to_frd(odom.twist.angular.to_array())
    pose_cov = frames.cov6_enu_flu_to_ned_frd(odom.pose_covariance.to_numpy()) if odom.pose_covariance is not None else None
    twist_cov = frames.cov6_flu_to_frd(odom.twist_covariance.to_numpy()) if odom.twist_covariance is not None else None

    def urt(c):
        if c is None:
            return [float("nan")] + [0.0] * 20
        return [float(c[i, j]) for i in range(6) for j in range(i, 6)]

    return dict(time_usec=time_usec, frame_id=mavlink.MAV_FRAME_LOCAL_FRD, child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
                x=float(p[0]), y=float(p[1]), z=float(p[2]), q=[float(x) for x in q],
                vx=float(v_body[0]), vy=float(v_body[1]), vz=float(v_body[2]),
                rollspeed=float(w_body[0]), pitchspeed=float(w_body[1]), yawspeed=float(w_body[2]),
                pose_covariance=urt(pose_cov), velocity_covariance=urt(twist_cov), reset_counter=odom.reset_counter % 256,
                estimator_type=mavlink.MAV_ESTIMATOR_TYPE_VISION, quality=odom.quality_pct or 0)


def parse_global_origin(text: str) -> tuple[float, float, float] | None:
    """global_origin 'LAT,LON,ALT_M' -> (lat_deg, lon_deg, alt_amsl_m); '' -> None; anything else
    refused naming the parameter."""
    if not text.strip():
        return None
    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"global_origin {text!r}: expected 'LAT,LON,ALT_M', e.g. '47.397742,8.545594,489.4'") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(alt)):
        raise ValueError(f"global_origin {text!r}: latitude within +-90, longitude within +-180, a finite altitude")
    return lat, lon, alt


class CommandWaiter:
    """Matches COMMAND_ACKs to the command a queryable is waiting for (one waiter per command id)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._waiting: dict[int, tuple[threading.Event, list]] = {}

    def expect(self, command: int) -> tuple[threading.Event, list]:
        ev, box = threading.Event(), []
        with self._lock:
            self._waiting[command] = (ev, box)
        return ev, box

    def on_ack(self, m) -> None:
        with self._lock:
            entry = self._waiting.pop(m.command, None)
        if entry:
            entry[1].append(m.result)
            entry[0].set()


def ack_name(result: int) -> str:
    enum = mavlink.enums["MAV_RESULT"]
    return enum[result].name.removeprefix("MAV_RESULT_") if result in enum else str(result)
