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

Parameters are read as p["NAME"], ~7x faster than p.NAME (a failed attribute lookup, then
ParamSet.__getattr__): a physics step at 400 Hz reads a dozen.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from aeroperception.services.mavlink.frames import (
    quat_conjugate, quat_from_axis_angle, quat_from_euler, quat_multiply, quat_normalize,
    quat_to_rotmat, quat_to_rotvec, yaw_from_q,
)
from aeroperception.services.runtime.params import ParamSet
from aeroperception.services.sim.truth import VehicleTruth

from .control import GRAVITY_MPS2, AttitudeThrust

_GRAVITY_ENU = np.array([0.0, 0.0, -GRAVITY_MPS2])
_GUST_AXES = np.array([1.0, 1.0, 1.0 / 3.0])   # gust std-dev per axis over SIM_WIND_GUST (vertical at a third)

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
        return yaw_from_q(self.q_enu_flu)

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
        return max(0.0, 1.0 - self.used_mah / self.p["SIM_BAT_CAP"])

    @property
    def voltage_v(self) -> float:
        p = self.p
        cell = p["BAT_V_EMPTY"] + (p["BAT_V_CHARGED"] - p["BAT_V_EMPTY"]) * self.remaining
        return max(0.0, p["SIM_BAT_CELLS"] * cell - self.current_a * p["SIM_BAT_R"])

    def step(self, dt_s: float, thrust_fraction: float, armed: bool) -> None:
        p = self.p
        self.current_a = (p["SIM_BAT_IDLE_A"] if armed else 0.1 * p["SIM_BAT_IDLE_A"]) \
            + p["SIM_BAT_MAX_A"] * max(thrust_fraction, 0.0) ** 1.5
        self.used_mah += self.current_a * dt_s / 3.6 * p["SIM_BAT_DRAIN"]


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
        self.gust_enu_mps = np.zeros(3)
        self._level_in, self._level_out = None, None   # _levelled's last (attitude, result)

    @property
    def max_thrust_n(self) -> float:
        return self.p["SIM_TWR"] * self.p["SIM_MASS"] * GRAVITY_MPS2

    def wind_enu_mps(self) -> np.ndarray:
        return np.array([self.p["SIM_WIND_E"], self.p["SIM_WIND_N"], 0.0]) + self.gust_enu_mps

    def _step_gust(self, dt_s: float) -> None:
        # Ornstein-Uhlenbeck: stationary std-dev SIM_WIND_GUST (vertical at a third), correlation
        # time SIM_GUST_TAU. Always draws, so the RNG stream does not depend on the wind settings.
        sigma = self.p["SIM_WIND_GUST"] * _GUST_AXES
        tau = self.p["SIM_GUST_TAU"]
        noise = self.rng.standard_normal(3)
        self.gust_enu_mps += -self.gust_enu_mps * (dt_s / tau) + sigma * math.sqrt(2.0 * dt_s / tau) * noise

    def _step_attitude(self, dt_s: float, q_sp: np.ndarray) -> None:
        s, p = self.state, self.p
        err = quat_to_rotvec(quat_multiply(quat_conjugate(s.q_enu_flu), q_sp))  # body frame
        rates = err / p["SIM_ATT_TAU"]
        max_rp, max_y = math.radians(p["MC_ROLLRATE_MAX"]), math.radians(p["MC_YAWRATE_MAX"])
        rates = np.clip(rates, [-max_rp, -max_rp, -max_y], [max_rp, max_rp, max_y])
        s.rates_flu_radps = rates
        s.q_enu_flu = quat_normalize(quat_multiply(s.q_enu_flu, quat_from_axis_angle(rates * dt_s)))

    def _levelled(self, q: np.ndarray) -> np.ndarray:
        """The level attitude with q's yaw. Resting, it is asked of the same q step after step
        (a fixed point within a few steps): the last answer is kept, as yaw_from_q and
        quat_from_euler cost ~15 us at 400 Hz, a quarter of a resting step."""
        key = q.tolist()
        if key != self._level_in:
            self._level_in, self._level_out = key, quat_from_euler(0.0, 0.0, yaw_from_q(q))
        return self._level_out.copy()

    def step(self, dt_s: float, command: AttitudeThrust | None) -> None:
        s, p = self.state, self.p
        self._step_gust(dt_s)

        thrust_cmd = 0.0 if command is None else min(max(command.thrust_n, 0.0), self.max_thrust_n)
        s.thrust_n += (thrust_cmd - s.thrust_n) * (1.0 - math.exp(-dt_s / p["SIM_THR_TAU"]))
        if command is not None:
            self._step_attitude(dt_s, command.q_enu_flu)
        else:
            s.rates_flu_radps = s.rates_flu_radps * math.exp(-dt_s / p["SIM_ATT_TAU"])  # tumbling decays
            s.q_enu_flu = quat_normalize(quat_multiply(s.q_enu_flu, quat_from_axis_angle(s.rates_flu_radps * dt_s)))

        body_z = quat_to_rotmat(s.q_enu_flu)[:, 2]
        air_mps = s.velocity_enu_mps - self.wind_enu_mps()
        accel = body_z * (s.thrust_n / p["SIM_MASS"]) + _GRAVITY_ENU - p["SIM_DRAG"] * air_mps

        # Ground: it pushes back when we press into it, and holds us (friction, level frame)
        # until thrust exceeds weight.
        s.on_ground = s.position_enu_m[2] <= s.ground_z_m + 1e-6
        s.resting = s.on_ground and accel[2] <= 0.0
        if s.resting:
            accel = np.zeros(3)
            s.velocity_enu_mps = np.zeros(3)
            s.q_enu_flu = self._levelled(s.q_enu_flu)
            s.rates_flu_radps = np.zeros(3)
        v_prev = s.velocity_enu_mps
        s.velocity_enu_mps = v_prev + accel * dt_s
        s.position_enu_m = s.position_enu_m + s.velocity_enu_mps * dt_s
        s.ground_z_m = float(self.terrain(s.position_enu_m[0], s.position_enu_m[1]))
        if s.position_enu_m[2] < s.ground_z_m:  # touchdown this step: stop on the surface
            s.position_enu_m[2] = s.ground_z_m
            s.velocity_enu_mps = np.array([s.velocity_enu_mps[0], s.velocity_enu_mps[1], 0.0])
        s.accel_enu_mps2 = (s.velocity_enu_mps - v_prev) / dt_s

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
