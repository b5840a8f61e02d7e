"""vio's configuration: every parameter of contract.PARAMS, referenced once. All are read at start
(contract.PARAMS are start_only): the strategy is built from `strategy_config()` then.

The algorithm's own config classes (FrontEndConfig, BackendConfig, ImuNoise, DriftConfig,
VioConfig) hold many more tunables than the parameters expose, and the defaults of those the
parameters do expose: the contract's defaults are read from them, never copied.
"""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param

from .backend import BackendConfig
from .drift import DriftConfig
from .frontend import FrontEndConfig
from .imu import ImuNoise
from .strategy import VioConfig


@dataclass(frozen=True)
class VioServiceConfig:
    strategy: str = param("strategy")
    max_features: int = param("max_features")
    keyframe_max_age_s: float = param("keyframe_max_age_s")
    ransac_threshold_px: float = param("ransac_threshold_px")
    lag_s: float = param("lag_s")
    covariance_every_frames: int = param("covariance_every_frames")
    lost_after_frames: int = param("lost_after_frames")
    gyro_noise_density: float = param("gyro_noise_density")
    accel_noise_density: float = param("accel_noise_density")
    gyro_random_walk: float = param("gyro_random_walk")
    accel_random_walk: float = param("accel_random_walk")
    drift_xy_frac: float = param("drift_xy_pct", lambda pct: pct / 100)
    drift_z_frac: float = param("drift_z_pct", lambda pct: pct / 100)
    imu_gap_warn_s: float = param("imu_gap_warn_s")
    imu_gap_reset_s: float = param("imu_gap_reset_s")
    imu_wait_s: float = param("imu_wait_s")
    imu_rate_hz: float = param("imu_rate_hz")
    imu_rate_max_horizon_s: float = param("imu_rate_max_horizon_s")
    opencv_threads: int = param("opencv_threads")

    def imu_noise(self) -> ImuNoise:
        return ImuNoise(gyro_noise_density=self.gyro_noise_density, accel_noise_density=self.accel_noise_density,
                        gyro_random_walk=self.gyro_random_walk, accel_random_walk=self.accel_random_walk)

    def strategy_config(self) -> VioConfig:
        """The strategy's configuration: the algorithm's defaults with the parameters' values."""
        return VioConfig(
            frontend=FrontEndConfig(max_features=self.max_features, keyframe_max_age_s=self.keyframe_max_age_s,
                                    ransac_threshold_px=self.ransac_threshold_px),
            backend=BackendConfig(lag_s=self.lag_s, covariance_every_frames=self.covariance_every_frames),
            imu=self.imu_noise(),
            drift=DriftConfig(drift_xy_frac=self.drift_xy_frac, drift_z_frac=self.drift_z_frac),
            lost_after_frames=self.lost_after_frames, imu_gap_warn_s=self.imu_gap_warn_s,
            imu_gap_reset_s=self.imu_gap_reset_s)
