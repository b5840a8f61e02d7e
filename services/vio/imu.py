"""The one IMU preintegration helper (requirement VIO-8): GTSAM's
PreintegratedCombinedMeasurements configured from the IMU's noise densities, fed with samples
clipped to a time window. The back end, `aero eval vio` and the tests all integrate through it.

Continuous-time densities as in Kalibr / EuRoC sensor.yaml: gyro noise rad/s/sqrt(Hz), accel
noise m/s^2/sqrt(Hz), gyro random walk rad/s^2/sqrt(Hz), accel random walk m/s^3/sqrt(Hz).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from .dto import ImuBias, ImuSample

GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class ImuNoise:
    """Defaults: requirement VIO-2 (what the simulator's IMU is configured with)."""

    gyro_noise_density: float = 0.005
    accel_noise_density: float = 0.01
    gyro_random_walk: float = 4.0e-6
    accel_random_walk: float = 2.0e-4
    integration_sigma: float = 1e-4
    gravity_mps2: float = GRAVITY_MPS2

    @classmethod
    def euroc(cls) -> "ImuNoise":
        """The ADIS16448 of EuRoC (mav0/imu0/sensor.yaml)."""
        return cls(gyro_noise_density=1.6968e-4, accel_noise_density=2.0e-3,
                   gyro_random_walk=1.9393e-5, accel_random_walk=3.0e-3)


def preintegration_params(noise: ImuNoise) -> gtsam.PreintegrationCombinedParams:
    """World z up, gravity (0, 0, -g) in the world: the IMU reads +g on its up axis at rest."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(noise.gravity_mps2)
    eye = np.eye(3)
    p.setGyroscopeCovariance(noise.gyro_noise_density ** 2 * eye)
    p.setAccelerometerCovariance(noise.accel_noise_density ** 2 * eye)
    p.setBiasOmegaCovariance(noise.gyro_random_walk ** 2 * eye)
    p.setBiasAccCovariance(noise.accel_random_walk ** 2 * eye)
    p.setIntegrationCovariance(noise.integration_sigma ** 2 * eye)
    return p


def to_gtsam_bias(bias: ImuBias) -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.asarray(bias.accel_mps2, float), np.asarray(bias.gyro_radps, float))


def from_gtsam_bias(b: gtsam.imuBias.ConstantBias) -> ImuBias:
    return ImuBias(accel_mps2=np.array(b.accelerometer()), gyro_radps=np.array(b.gyroscope()))


class ImuPreintegrator:
    """Preintegrates the samples of [t0, t1] on top of a bias estimate (zero-order hold: each
    sample holds until the next one; the window's ends are clipped exactly)."""

    def __init__(self, noise: ImuNoise):
        self.noise = noise
        self.params = preintegration_params(noise)

    def integrate(self, samples: Sequence[ImuSample], t0_ns: int, t1_ns: int,
                  bias: ImuBias | gtsam.imuBias.ConstantBias | None = None
                  ) -> gtsam.PreintegratedCombinedMeasurements:
        """Samples must be sorted by time. The sample in force at t0 is the last one at or before
        t0 (or the first one, when none is that early); the last sample holds until t1."""
        b = bias if isinstance(bias, gtsam.imuBias.ConstantBias) else to_gtsam_bias(bias or ImuBias())
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, b)
        if t1_ns <= t0_ns or not samples:
            return pim
        start = 0
        for i, s in enumerate(samples):
            if s.t_ns <= t0_ns:
                start = i
            else:
                break
        for i in range(start, len(samples)):
            s = samples[i]
            a = max(s.t_ns, t0_ns)
            b_end = samples[i + 1].t_ns if i + 1 < len(samples) else t1_ns
            b_end = min(b_end, t1_ns)
            if b_end > a:
                pim.integrateMeasurement(s.accel_mps2, s.gyro_radps, (b_end - a) * 1e-9)
            if b_end >= t1_ns:
                break
        return pim

    @staticmethod
    def predict(pim: gtsam.PreintegratedCombinedMeasurements, world_T_body: np.ndarray,
                velocity_world_mps: np.ndarray, bias: ImuBias | gtsam.imuBias.ConstantBias
                ) -> tuple[np.ndarray, np.ndarray]:
        """(world_T_body, velocity) at the window's end, from the state at its start."""
        b = bias if isinstance(bias, gtsam.imuBias.ConstantBias) else to_gtsam_bias(bias)
        nav = gtsam.NavState(gtsam.Pose3(world_T_body), np.asarray(velocity_world_mps, float))
        out = pim.predict(nav, b)
        return out.pose().matrix(), np.array(out.velocity())


def gravity_aligned_rotation(mean_accel_body_mps2: np.ndarray, yaw_rad: float = 0.0) -> np.ndarray:
    """R_world_body that maps the measured specific force at rest onto world +z (the smallest
    rotation doing so), then yawed by `yaw_rad` about world z. Yaw is unobservable from the IMU."""
    a = np.asarray(mean_accel_body_mps2, float)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n < 1e-6:
        raise ValueError("no specific force measured: cannot find gravity")
    u = a / n
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s, c = np.linalg.norm(v), float(u @ z)
    if s < 1e-12:
        r = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = v / s
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        ang = np.arctan2(s, c)
        r = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * kx @ kx
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]]) @ r
