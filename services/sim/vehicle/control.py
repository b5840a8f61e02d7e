"""Multirotor position control, shaped like PX4's mc_pos_control.

Cascade: position P -> velocity PID -> acceleration -> thrust vector (tilt-limited) + yaw ->
attitude setpoint and collective thrust. Everything is ENU world / FLU body; NED exists only
on the MAVLink side. Setpoints follow PX4's TrajectorySetpoint convention: NaN means "not
controlled", per axis, so one type carries position, velocity and mixed setpoints.
The cascade computes on plain floats (floats.py): it runs every physics step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from aeroperception.services.mavlink.frames import quat_from_rotmat
from aeroperception.services.runtime.params import ParamSet

from .floats import clip, floats, or_zero

GRAVITY_MPS2 = 9.80665
_NAN3 = (math.nan, math.nan, math.nan)


def _nan3() -> np.ndarray:
    return np.array(_NAN3)


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
    """Attitude whose body z is along f (three floats) and whose heading is yaw (PX4 bodyzToAttitude)."""
    fx, fy, fz = f_enu
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
        self._vel_int = (0.0, 0.0, 0.0)   # velocity integrator (ENU m/s^2)
        self._yaw_sp: float | None = None

    def reset(self) -> None:
        self._vel_int = (0.0, 0.0, 0.0)
        self._yaw_sp = None

    def update(self, dt_s: float, sp: Setpoint, position_enu_m: np.ndarray, velocity_enu_mps: np.ndarray,
               accel_enu_mps2: np.ndarray, yaw_rad: float, landed: bool) -> AttitudeThrust:
        p = self.p
        mass = p.SIM_MASS
        f_max = p.SIM_TWR * GRAVITY_MPS2  # specific thrust at full throttle

        if landed and not sp.wants_climb(position_enu_m):
            # On the ground and not asked to climb: motors at idle, integrators held at zero,
            # as PX4's takeoff handling does (this is also what lets the land detector trigger).
            self.reset()
            return AttitudeThrust(attitude_from_thrust_dir((0.0, 0.0, 1.0), yaw_rad), 0.0)

        # --- yaw ---
        if math.isfinite(sp.yaw_rad):
            self._yaw_sp = sp.yaw_rad
        elif self._yaw_sp is None:
            self._yaw_sp = yaw_rad
        if math.isfinite(sp.yaw_rate_radps) and not math.isfinite(sp.yaw_rad):
            self._yaw_sp += sp.yaw_rate_radps * dt_s

        # --- position P -> velocity setpoint (with feed-forward), limited ---
        x, y, z = floats(position_enu_m)
        x_sp, y_sp, z_sp = floats(sp.position_enu_m)
        vx_ff, vy_ff, vz_ff = floats(sp.velocity_enu_mps)
        vx_sp = p.MPC_XY_P * or_zero(x_sp - x) + or_zero(vx_ff)
        vy_sp = p.MPC_XY_P * or_zero(y_sp - y) + or_zero(vy_ff)
        vz_sp = p.MPC_Z_P * or_zero(z_sp - z) + or_zero(vz_ff)
        max_xy = min(p.MPC_XY_VEL_MAX, sp.max_xy_mps)
        speed_xy = math.hypot(vx_sp, vy_sp)
        if speed_xy > max_xy:
            k = max_xy / speed_xy
            vx_sp, vy_sp = vx_sp * k, vy_sp * k
        vz_sp = clip(vz_sp, -min(p.MPC_Z_VEL_MAX_DN, sp.max_down_mps), min(p.MPC_Z_VEL_MAX_UP, sp.max_up_mps))

        # --- velocity PID -> acceleration setpoint ---
        vx, vy, vz = floats(velocity_enu_mps)
        ex, ey, ez = vx_sp - vx, vy_sp - vy, vz_sp - vz
        ax, ay, az = floats(accel_enu_mps2)
        ax_ff, ay_ff, az_ff = floats(sp.accel_enu_mps2)
        ix, iy, iz = self._vel_int
        kp_xy, kd_xy = p.MPC_XY_VEL_P_ACC, p.MPC_XY_VEL_D_ACC
        ax_sp = kp_xy * ex + ix - kd_xy * ax + or_zero(ax_ff)
        ay_sp = kp_xy * ey + iy - kd_xy * ay + or_zero(ay_ff)
        az_sp = p.MPC_Z_VEL_P_ACC * ez + iz - p.MPC_Z_VEL_D_ACC * az + or_zero(az_ff)

        # --- acceleration -> thrust vector, vertical first, then tilt and thrust limits ---
        f_x, f_y, f_z_wanted = ax_sp, ay_sp, az_sp + GRAVITY_MPS2
        f_z = clip(f_z_wanted, p.MPC_THR_MIN * f_max, f_max)
        f_xy_max = min(f_z * math.tan(math.radians(p.MPC_TILTMAX_AIR)), math.sqrt(max(f_max**2 - f_z**2, 0.0)))
        n_xy = math.hypot(f_x, f_y)
        saturated_xy = n_xy > f_xy_max
        if saturated_xy:
            f_x, f_y = f_x * (f_xy_max / n_xy), f_y * (f_xy_max / n_xy)

        # Integrate only where the output is not saturated (anti-windup), and bound it.
        if not saturated_xy:
            ix, iy = ix + p.MPC_XY_VEL_I_ACC * ex * dt_s, iy + p.MPC_XY_VEL_I_ACC * ey * dt_s
        if f_z == f_z_wanted:
            iz += p.MPC_Z_VEL_I_ACC * ez * dt_s
        bound = GRAVITY_MPS2 / 2
        self._vel_int = (clip(ix, -bound, bound), clip(iy, -bound, bound), clip(iz, -bound, bound))

        thrust_n = mass * math.sqrt(f_x * f_x + f_y * f_y + f_z * f_z)
        return AttitudeThrust(attitude_from_thrust_dir((f_x, f_y, f_z), self._yaw_sp), thrust_n)
