"""The VIO data types of requirement VIO-7 (plain dataclasses: they never travel on Zenoh; the
service maps them to Odometry / VioHealth) and its error types.

Frames: `body` is the IMU frame (FLU on our vehicles; whatever the dataset's IMU is otherwise),
`world` is VIO's gravity-aligned odom frame (z up, origin and yaw where VIO initialised).
Poses are 4x4 homogeneous matrices T_a_b (maps b coordinates into a). Covariances of poses are
6x6 in the order x, y, z, roll, pitch, yaw (as Odometry), world-aligned axes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class VioError(RuntimeError):
    """Base of the VIO errors."""


class VioInitializingError(VioError):
    """Not initialised yet (waiting for IMU, calibration or a first good stereo frame): no output."""


class VioDegradedError(VioError):
    """This frame's estimate is weak (few features, IMU gap); an output is still attached, with
    inflated covariance, in `.output`."""

    def __init__(self, message: str, output: "VioOutput | None" = None):
        super().__init__(message)
        self.output = output


class VioFatalError(VioError):
    """The strategy cannot go on (lost for too long, broken input): reset_to_warm_start needed."""


class StrategyNotAvailableError(VioError):
    """The requested strategy is not built into this installation; the message lists what is."""


@dataclass
class ImuSample:
    """One IMU reading in the body frame: rad/s and specific force m/s^2 (gravity included)."""

    t_ns: int
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray


@dataclass
class ImuWindow:
    """The IMU samples between the previous frame and this one (VIO-7: they bracket the frame)."""

    start_t_ns: int
    end_t_ns: int
    samples: list[ImuSample] = field(default_factory=list)


@dataclass
class NavCameraFrame:
    """A stereo pair taken at one instant (right is None for a mono camera)."""

    frame_id: int
    capture_timestamp_ns: int
    left: np.ndarray           # (H, W) uint8 or (H, W, 3) RGB
    right: np.ndarray | None = None
    camera_id: str = "stereo"


@dataclass
class ImuBias:
    accel_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_radps: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def norm(self) -> float:
        return float(np.linalg.norm(np.concatenate([self.accel_mps2, self.gyro_radps])))


@dataclass
class WarmStartPose:
    """Pose hint to restart from (VIO-6): body pose in world, world velocity, bias."""

    world_T_body: np.ndarray
    velocity_world_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias: ImuBias = field(default_factory=ImuBias)


@dataclass
class FeatureQuality:
    tracked: int = 0
    lost: int = 0
    inliers: int = 0
    mean_parallax_px: float = 0.0
    mean_reprojection_error_px: float = 0.0


@dataclass
class VioOutput:
    """One frame's result. `relative_pose_T` is the body motion since the last keyframe
    (VIO-7); `world_T_body` etc. are the smoother's current estimate, which state/visual_odometry
    carries."""

    frame_id: int
    stamp_ns: int
    relative_pose_T: np.ndarray
    pose_covariance_6x6: np.ndarray
    imu_bias: ImuBias
    feature_quality: FeatureQuality
    world_T_body: np.ndarray
    velocity_world_mps: np.ndarray
    angular_velocity_body_radps: np.ndarray
    twist_covariance_6x6: np.ndarray
    keyframe: bool = False
    timings_ms: dict[str, float] = field(default_factory=dict)
    emitted_at_ns: int = 0
    reset_counter: int = 0        # re-initialisations so far: the pose may jump where it changes
    quality_pct: int = 1          # health.quality_pct: 1 (IMU only) - 100 (a full visual fix)


# Health states: the values of schemas VioHealth.state.
INIT, TRACKING, DEGRADED, LOST = 0, 1, 2, 3
STATE_NAMES = {INIT: "INIT", TRACKING: "TRACKING", DEGRADED: "DEGRADED", LOST: "LOST"}


@dataclass
class StrategyHealth:
    """A strategy's own health record (messages.health makes the VioHealth message of it)."""

    state: int = INIT
    consecutive_lost: int = 0
    bias_norm: float = 0.0
    message: str = "waiting for IMU and calibration"

    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.state]
