"""Multirotor physics: point mass with a first-order attitude response, over the scenario's terrain.

Deliberately simple (the autonomy stack only needs PX4-like closed-loop behaviour, not rotor
aerodynamics): thrust along body +z with a motor lag, linear drag against the air, constant wind
plus Ornstein-Uhlenbeck gusts, an attitude that converges to its setpoint with one time constant
(what PX4's rate/attitude loops look like from outside), ground contact, and a battery whose
current follows thrust. ENU world, FLU body, SI units. Deterministic for a given RNG.

The ground is a height field z = terrain(x, y) (ENU m; flat z = 0 by default, the scenario's
ground plane in the simulator), so touchdown, resting and take-off happen on a slope where the
rendered sensors see it. A vehicle resting on a slope keeps a level frame (its legs take the
slope), as it did on flat ground.

The step computes on plain floats (floats.py: numpy costs ~1 us per call on 3-vectors) and
stores numpy vectors in RigidBodyState, which the estimator, commander and telemetry read.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from aeroperception.services.mavlink.frames import quat_from_euler, quat_to_rotmat
from aeroperception.services.runtime.params import ParamSet
from aeroperception.services.sim.truth import VehicleTruth

from .control import GRAVITY_MPS2, AttitudeThrust
from .floats import (
    Quat, Vec3, array, body_z, clip, floats, quat_conj, quat_from_axis_angle, quat_mul, quat_normalize,
    quat_to_rotvec, yaw_of,
)

_GRAVITY_ENU = np.array([0.0, 0.0, -GRAVITY_MPS2])
_GUST_Z = 1.0 / 3.0   # vertical gust std-dev over SIM_WIND_GUST (horizontal: 1)

Terrain = Callable[[float, float], float]   # ground z (ENU m) under (x, y)


def flat_ground(x_m: float, y_m: float) -> float:
    return 0.0


@dataclass
class RigidBodyState:
    position_enu_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity_enu_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_enu_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q_enu_flu: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    rates_flu_radps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    thrust_n: float = 0.0
    on_ground: bool = True        # touching the ground
    resting: bool = True          # on the ground and not lifting off (held by the ground)
    ground_z_m: float = 0.0       # terrain height under the vehicle (ENU z)

    @property
    def height_agl_m(self) -> float:
        """Height of the vehicle above the terrain under it."""
        return float(self.position_enu_m[2]) - self.ground_z_m

    @property
    def yaw_rad(self) -> float:
        return yaw_of(floats(self.q_enu_flu))

    def specific_force_flu_mps2(self) -> np.ndarray:
        """What an ideal accelerometer reads: R^T (a - g), +9.81 up when at rest."""
        return quat_to_rotmat(self.q_enu_flu).T @ (self.accel_enu_mps2 - _GRAVITY_ENU)


class Battery:
    """Coulomb-counting pack with a linear open-circuit voltage and an IR sag (PX4's model)."""

    def __init__(self, params: ParamSet):
        self.p = params
        self.used_mah = 0.0
        self.current_a = 0.0

    @property
    def remaining(self) -> float:
        """Fraction 0..1."""
        return max(0.0, 1.0 - self.used_mah / self.p.SIM_BAT_CAP)

    @property
    def voltage_v(self) -> float:
        p = self.p
        cell = p.BAT_V_EMPTY + (p.BAT_V_CHARGED - p.BAT_V_EMPTY) * self.remaining
        return max(0.0, p.SIM_BAT_CELLS * cell - self.current_a * p.SIM_BAT_R)

    def step(self, dt_s: float, thrust_fraction: float, armed: bool) -> None:
        p = self.p
        self.current_a = (p.SIM_BAT_IDLE_A if armed else 0.1 * p.SIM_BAT_IDLE_A) \
            + p.SIM_BAT_MAX_A * max(thrust_fraction, 0.0) ** 1.5
        self.used_mah += self.current_a * dt_s / 3.6 * p.SIM_BAT_DRAIN


class Multirotor:
    """The airframe. `step(dt, command)`; command None means motors stopped (disarmed)."""

    def __init__(self, params: ParamSet, rng: np.random.Generator, yaw_rad: float = 0.0,
                 terrain: Terrain | None = None):
        self.p = params
        self.rng = rng
        self.terrain = terrain or flat_ground
        self.state = RigidBodyState(q_enu_flu=quat_from_euler(0.0, 0.0, yaw_rad))
        self.state.ground_z_m = float(self.terrain(0.0, 0.0))
        self.state.position_enu_m[2] = self.state.ground_z_m   # starts resting on the ground
        self.battery = Battery(params)
        self._gust: Vec3 = (0.0, 0.0, 0.0)
        self._level_in, self._level_out = None, None   # _levelled's last (attitude, result)

    @property
    def max_thrust_n(self) -> float:
        return self.p.SIM_TWR * self.p.SIM_MASS * GRAVITY_MPS2

    @property
    def gust_enu_mps(self) -> np.ndarray:
        return array(self._gust)

    def wind_enu_mps(self) -> np.ndarray:
        return array(self._wind())

    def _wind(self) -> Vec3:
        gx, gy, gz = self._gust
        return (self.p.SIM_WIND_E + gx, self.p.SIM_WIND_N + gy, 0.0 + gz)

    def _step_gust(self, dt_s: float) -> None:
        # Ornstein-Uhlenbeck: stationary std-dev SIM_WIND_GUST (vertical at a third), correlation
        # time SIM_GUST_TAU. Always draws, so the RNG stream does not depend on the wind settings.
        gust, tau = self.p.SIM_WIND_GUST, self.p.SIM_GUST_TAU
        decay, spread = dt_s / tau, math.sqrt(2.0 * dt_s / tau)
        step_xy, step_z = gust * spread, gust * _GUST_Z * spread
        gx, gy, gz = self._gust
        nx, ny, nz = self.rng.standard_normal(3).tolist()
        self._gust = (gx + (-gx * decay + step_xy * nx), gy + (-gy * decay + step_xy * ny),
                      gz + (-gz * decay + step_z * nz))

    def _step_attitude(self, dt_s: float, q: Quat, q_sp: Quat) -> tuple[Quat, Vec3]:
        """(attitude, body rates) after dt of the first-order response towards q_sp."""
        p = self.p
        tau = p.SIM_ATT_TAU
        max_rp, max_y = math.radians(p.MC_ROLLRATE_MAX), math.radians(p.MC_YAWRATE_MAX)
        ex, ey, ez = quat_to_rotvec(quat_mul(quat_conj(q), q_sp))   # body frame
        rates = (clip(ex / tau, -max_rp, max_rp), clip(ey / tau, -max_rp, max_rp), clip(ez / tau, -max_y, max_y))
        return self._rotated(q, rates, dt_s), rates

    @staticmethod
    def _rotated(q: Quat, rates: Vec3, dt_s: float) -> Quat:
        """q after turning at body rates for dt."""
        wx, wy, wz = rates
        return quat_normalize(quat_mul(q, quat_from_axis_angle((wx * dt_s, wy * dt_s, wz * dt_s))))

    def _levelled(self, q: Quat) -> Quat:
        """The level attitude with q's yaw. Resting, it is asked of the same q step after step
        (a fixed point within a few steps): the last answer is kept."""
        if q != self._level_in:
            self._level_in, self._level_out = q, floats(quat_from_euler(0.0, 0.0, yaw_of(q)))
        return self._level_out

    def step(self, dt_s: float, command: AttitudeThrust | None) -> None:
        s, p = self.state, self.p
        self._step_gust(dt_s)

        thrust_cmd = 0.0 if command is None else min(max(command.thrust_n, 0.0), self.max_thrust_n)
        s.thrust_n += (thrust_cmd - s.thrust_n) * (1.0 - math.exp(-dt_s / p.SIM_THR_TAU))
        q = floats(s.q_enu_flu)
        if command is not None:
            q, rates = self._step_attitude(dt_s, q, floats(command.q_enu_flu))
        else:
            decay = math.exp(-dt_s / p.SIM_ATT_TAU)   # tumbling decays
            wx, wy, wz = floats(s.rates_flu_radps)
            rates = (wx * decay, wy * decay, wz * decay)
            q = self._rotated(q, rates, dt_s)

        # Thrust along body z, gravity, drag against the air (ENU).
        thrust_acc, drag = s.thrust_n / p.SIM_MASS, p.SIM_DRAG
        bx, by, bz = body_z(q)
        wind_x, wind_y, wind_z = self._wind()
        v0x, v0y, v0z = floats(s.velocity_enu_mps)
        ax = bx * thrust_acc - drag * (v0x - wind_x)
        ay = by * thrust_acc - drag * (v0y - wind_y)
        az = bz * thrust_acc - GRAVITY_MPS2 - drag * (v0z - wind_z)

        # Ground: it pushes back when we press into it, and holds us (friction, level frame)
        # until thrust exceeds weight.
        x, y, z = floats(s.position_enu_m)
        s.on_ground = z <= s.ground_z_m + 1e-6
        s.resting = s.on_ground and az <= 0.0
        if s.resting:
            ax = ay = az = v0x = v0y = v0z = 0.0
            rates = (0.0, 0.0, 0.0)
            q = self._levelled(q)
        vx, vy, vz = v0x + ax * dt_s, v0y + ay * dt_s, v0z + az * dt_s
        x, y, z = x + vx * dt_s, y + vy * dt_s, z + vz * dt_s
        s.ground_z_m = float(self.terrain(x, y))
        if z < s.ground_z_m:  # touchdown this step: stop on the surface
            z, vz = s.ground_z_m, 0.0
        s.position_enu_m, s.velocity_enu_mps = array((x, y, z)), array((vx, vy, vz))
        s.accel_enu_mps2 = array(((vx - v0x) / dt_s, (vy - v0y) / dt_s, (vz - v0z) / dt_s))
        s.q_enu_flu, s.rates_flu_radps = array(q), array(rates)

        self.battery.step(dt_s, s.thrust_n / self.max_thrust_n, armed=command is not None)

    def truth(self, stamp_ns: int) -> VehicleTruth:
        s = self.state
        return VehicleTruth(
            stamp_ns=stamp_ns,
            position_enu_m=s.position_enu_m.copy(),
            velocity_enu_mps=s.velocity_enu_mps.copy(),
            accel_enu_mps2=s.accel_enu_mps2.copy(),
            q_enu_flu=s.q_enu_flu.copy(),
            angular_velocity_flu_radps=s.rates_flu_radps.copy(),
        )
