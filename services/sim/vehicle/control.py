"""Multirotor position control, shaped like PX4's mc_pos_control.

Cascade: position P -> velocity PID -> acceleration -> thrust vector (tilt-limited) + yaw ->
attitude setpoint and collective thrust. Everything is ENU world / FLU body; NED exists only
on the MAVLink side. Setpoints follow PX4's TrajectorySetpoint convention: NaN means "not
controlled", per axis, so one type carries position, velocity and mixed setpoints.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from aeroperception.services.mavlink.frames import quat_from_rotmat
from aeroperception.services.runtime.params import ParamSet

GRAVITY_MPS2 = 9.80665
_NAN3 = (math.nan, math.nan, math.nan)


def _nan3() -> np.ndarray:
    return np.array(_NAN3)


def _or_zero(a: np.ndarray) -> np.ndarray:
    """NaN ("not controlled") -> 0. Cheaper than np.nan_to_num, which also handles infinities."""
    return np.where(np.isfinite(a), a, 0.0)


@dataclass
class Setpoint:
    """What the vehicle should do now, ENU. NaN components are not controlled; velocity and
    acceleration alongside a position act as feed-forward. Speed limits, when set, tighten the
    MPC_* limits (auto modes use them for takeoff, landing and cruise speeds)."""

    position_enu_m: np.ndarray = field(default_factory=_nan3)
    velocity_enu_mps: np.ndarray = field(default_factory=_nan3)
    accel_enu_mps2: np.ndarray = field(default_factory=_nan3)
    yaw_rad: float = math.nan
    yaw_rate_radps: float = math.nan
    max_xy_mps: float = math.inf
    max_up_mps: float = math.inf
    max_down_mps: float = math.inf

    @classmethod
    def hold(cls, position_enu_m, yaw_rad: float) -> "Setpoint":
        return cls(position_enu_m=np.array(position_enu_m, dtype=float), yaw_rad=yaw_rad)

    def wants_climb(self, position_enu_m: np.ndarray) -> bool:
        """PX4's takeoff trigger: a position setpoint 0.2 m above us or an upward velocity."""
        z_sp, vz_sp = self.position_enu_m[2], self.velocity_enu_mps[2]
        return bool((math.isfinite(z_sp) and z_sp > position_enu_m[2] + 0.2)
                    or (math.isfinite(vz_sp) and vz_sp > 0.3))


@dataclass
class AttitudeThrust:
    """Output of position control, input of the airframe: desired attitude (ENU <- FLU) and
    collective thrust along body +z."""

    q_enu_flu: np.ndarray
    thrust_n: float


def attitude_from_thrust_dir(f_enu, yaw_rad: float) -> np.ndarray:
    """Attitude whose body z is along f and whose heading is yaw (PX4 bodyzToAttitude).
    Plain floats: this runs every physics step and numpy's overhead dominates at size 3."""
    fx, fy, fz = (float(v) for v in f_enu)
    n = math.sqrt(fx * fx + fy * fy + fz * fz)
    zx, zy, zz = fx / n, fy / n, fz / n
    cx, cy = math.cos(yaw_rad), math.sin(yaw_rad)
    # y_b = z_b x x_c, with x_c = (cx, cy, 0)
    yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
    n = math.sqrt(yx * yx + yy * yy + yz * yz)
    if n > 1e-6:
        yx, yy, yz = yx / n, yy / n, yz / n
    else:  # thrust horizontal and along the heading: any perpendicular will do
        yx, yy, yz = -cy, cx, 0.0
    # x_b = y_b x z_b
    xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
    return quat_from_rotmat(((xx, yx, zx), (xy, yy, zy), (xz, yz, zz)))


class PositionController:
    """Stateful (integrators, yaw setpoint) cascade; call `update` once per physics step."""

    def __init__(self, params: ParamSet):
        self.p = params
        self._vel_int = np.zeros(3)
        self._yaw_sp: float | None = None

    def reset(self) -> None:
        self._vel_int[:] = 0.0
        self._yaw_sp = None

    def update(self, dt_s: float, sp: Setpoint, position_enu_m: np.ndarray, velocity_enu_mps: np.ndarray,
               accel_enu_mps2: np.ndarray, yaw_rad: float, landed: bool) -> AttitudeThrust:
        p = self.p   # p["NAME"]: ~7x faster than p.NAME (a failed attribute lookup, then __getattr__) at 400 Hz
        mass = p["SIM_MASS"]
        f_max = p["SIM_TWR"] * GRAVITY_MPS2  # specific thrust at full throttle

        if landed and not sp.wants_climb(position_enu_m):
            # On the ground and not asked to climb: motors at idle, integrators held at zero,
            # as PX4's takeoff handling does (this is also what lets the land detector trigger).
            self.reset()
            return AttitudeThrust(attitude_from_thrust_dir(np.array([0.0, 0.0, 1.0]), yaw_rad), 0.0)

        # --- yaw ---
        if math.isfinite(sp.yaw_rad):
            self._yaw_sp = sp.yaw_rad
        elif self._yaw_sp is None:
            self._yaw_sp = yaw_rad
        if math.isfinite(sp.yaw_rate_radps) and not math.isfinite(sp.yaw_rad):
            self._yaw_sp += sp.yaw_rate_radps * dt_s

        # --- position P -> velocity setpoint (with feed-forward), limited ---
        pos_err = sp.position_enu_m - position_enu_m
        gains = np.array([p["MPC_XY_P"], p["MPC_XY_P"], p["MPC_Z_P"]])
        vel_sp = gains * _or_zero(pos_err)
        vel_sp += _or_zero(sp.velocity_enu_mps)
        max_xy = min(p["MPC_XY_VEL_MAX"], sp.max_xy_mps)
        speed_xy = math.hypot(vel_sp[0], vel_sp[1])
        if speed_xy > max_xy:
            vel_sp[:2] *= max_xy / speed_xy
        vel_sp[2] = min(max(vel_sp[2], -min(p["MPC_Z_VEL_MAX_DN"], sp.max_down_mps)),
                        min(p["MPC_Z_VEL_MAX_UP"], sp.max_up_mps))

        # --- velocity PID -> acceleration setpoint ---
        vel_err = vel_sp - velocity_enu_mps
        kp = np.array([p["MPC_XY_VEL_P_ACC"], p["MPC_XY_VEL_P_ACC"], p["MPC_Z_VEL_P_ACC"]])
        ki = np.array([p["MPC_XY_VEL_I_ACC"], p["MPC_XY_VEL_I_ACC"], p["MPC_Z_VEL_I_ACC"]])
        kd = np.array([p["MPC_XY_VEL_D_ACC"], p["MPC_XY_VEL_D_ACC"], p["MPC_Z_VEL_D_ACC"]])
        acc_sp = kp * vel_err + self._vel_int - kd * accel_enu_mps2 + _or_zero(sp.accel_enu_mps2)

        # --- acceleration -> thrust vector, vertical first, then tilt and thrust limits ---
        f = acc_sp + np.array([0.0, 0.0, GRAVITY_MPS2])
        f_z = min(max(f[2], p["MPC_THR_MIN"] * f_max), f_max)
        f_xy_max = min(f_z * math.tan(math.radians(p["MPC_TILTMAX_AIR"])), math.sqrt(max(f_max**2 - f_z**2, 0.0)))
        f_xy = f[:2]
        n_xy = math.hypot(f_xy[0], f_xy[1])
        saturated_xy = n_xy > f_xy_max
        if saturated_xy:
            f_xy = f_xy * (f_xy_max / n_xy)
        f_lim = np.array([f_xy[0], f_xy[1], f_z])

        # Integrate only where the output is not saturated (anti-windup), and bound it.
        grow = np.array([not saturated_xy, not saturated_xy, f_z == f[2]])
        self._vel_int += np.where(grow, ki * vel_err * dt_s, 0.0)
        np.clip(self._vel_int, -GRAVITY_MPS2 / 2, GRAVITY_MPS2 / 2, out=self._vel_int)

        return AttitudeThrust(attitude_from_thrust_dir(f_lim, self._yaw_sp), mass * float(np.linalg.norm(f_lim)))
