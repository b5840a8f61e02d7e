"""The lidar service's configuration: every parameter of contract.PARAMS, referenced once (the
runtime rebuilds it on a live change and calls LidarService.on_config once)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aeroperception.services.runtime import param, section
from aeroperception.services.runtime.rotations import quat_from_euler, quat_to_rotmat

from .costmap import CostmapConfig
from .pipeline import PipelineConfig


@dataclass(frozen=True)
class MountConfig:
    """Where the sensor sits on the body (FLU): offset in metres, attitude in degrees."""

    x_m: float = param("mount_x_m")
    y_m: float = param("mount_y_m")
    z_m: float = param("mount_z_m")
    roll_deg: float = param("mount_roll_deg")
    pitch_deg: float = param("mount_pitch_deg")
    yaw_deg: float = param("mount_yaw_deg")

    def body_sensor(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_body_sensor, t_body_sensor)."""
        r = quat_to_rotmat(quat_from_euler(*np.radians([self.roll_deg, self.pitch_deg, self.yaw_deg])))
        return r, np.array([self.x_m, self.y_m, self.z_m])


@dataclass(frozen=True)
class LidarConfig:
    pipeline: PipelineConfig = section(PipelineConfig)     # the filter stages (pipeline.py)
    costmap: CostmapConfig = section(CostmapConfig)        # the rolling grid (costmap.py)
    mount: MountConfig = section(MountConfig)
    use_imu_tilt: bool = param("use_imu_tilt")
    processing_rate_hz: float = param("processing_rate_hz")
    pose_max_age_s: float = param("pose_max_age_s")
    ground_publish_period_s: float = param("ground_publish_period_s")
