"""IMU model: what a body-mounted IMU at the FLU body origin measures along the true trajectory.

Specific force f = R_enu_flu^T (a_world - g_world), g_world = (0, 0, -9.80665) ENU, so a vehicle
at rest or hovering reads +9.81 m/s^2 on body z. Noise follows the continuous-time model VIO is
configured with (requirement VIO-2 densities): per sample, white noise sigma = density / sqrt(dt)
and the bias random walk b += walk * sqrt(dt) * N(0, 1). Truth angular velocity and acceleration
come from the vehicle dynamics, so integrating the noiseless output reproduces the trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..world.scenario import ImuConfig
from .frames import pose_of

GRAVITY_MPS2 = 9.80665
G_ENU_MPS2 = np.array([0.0, 0.0, -GRAVITY_MPS2])


@dataclass
class ImuSample:
    stamp_ns: int
    angular_velocity_flu_radps: np.ndarray     # (3,) float64, body FLU
    linear_acceleration_flu_mps2: np.ndarray   # (3,) float64, specific force, body FLU
    frame_id: str = "base_link"


class ImuModel:
    """Stateful (the biases walk); one instance per simulated IMU. Deterministic per seed."""

    def __init__(self, config: ImuConfig | None = None, seed: int = 0):
        self.config = config or ImuConfig()
        self._seed = seed
        self.reset()

    def reset(self) -> None:
        c = self.config
        self._rng = np.random.default_rng([self._seed, 0x1417])
        self.gyro_bias_radps = np.array(c.initial_gyro_bias_radps, dtype=float)
        self.accel_bias_mps2 = np.array(c.initial_accel_bias_mps2, dtype=float)
        self._last_stamp_ns: int | None = None

    @staticmethod
    def ideal(truth) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free (angular velocity FLU rad/s, specific force FLU m/s^2) of a VehicleTruth."""
        _, r_wb = pose_of(truth)
        f = r_wb.T @ (np.asarray(truth.accel_enu_mps2, dtype=float) - G_ENU_MPS2)
        return np.array(truth.angular_velocity_flu_radps, dtype=float), f

    def sample(self, truth, dt_s: float | None = None) -> ImuSample:
        """Measurement at truth.stamp_ns. dt_s defaults to the time since the previous sample
        (1/rate_hz for the first one); it scales the discrete noise."""
        c = self.config
        if dt_s is None:
            last = self._last_stamp_ns
            dt_s = (truth.stamp_ns - last) * 1e-9 if last is not None and truth.stamp_ns > last else 1.0 / c.rate_hz
        self._last_stamp_ns = truth.stamp_ns
        gyro, accel = self.ideal(truth)
        if not c.noiseless:
            n = self._rng.standard_normal(12)
            sq = np.sqrt(dt_s)
            self.gyro_bias_radps += c.gyro_random_walk * sq * n[0:3]
            self.accel_bias_mps2 += c.accel_random_walk * sq * n[3:6]
            gyro = gyro + self.gyro_bias_radps + (c.gyro_noise_density / sq) * n[6:9]
            accel = accel + self.accel_bias_mps2 + (c.accel_noise_density / sq) * n[9:12]
        return ImuSample(int(truth.stamp_ns), gyro, accel)
