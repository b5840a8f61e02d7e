"""Sensor, perception and health messages: the ROS sensor_msgs / nav_msgs / vision_msgs /
diagnostic_msgs equivalents the stack needs, plus VIO health and the perception verdict built on it.

Arrays (pixels, points, covariances) are NDArray so any msgpack reader gets {dtype, shape,
data}; shapes and dtypes are checked on decode so a consumer never indexes a malformed buffer.
Body quantities are FLU, world quantities ENU; no NED here (only fmu and gcs see NED).
"""
from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from ._base import Header, Message, NDArray, schema
from ._checks import check_choice, check_dtype, enum_names
from .geometry import Pose, Quaternion, Twist, Vector3

__all__ = [
    "Imu", "Image", "CameraInfo", "PointCloud", "OccupancyGrid", "Detection2D", "Detection2DArray",
    "BatteryState", "DiagnosticStatus", "DiagnosticArray", "Odometry", "VioHealth", "PerceptionHealth",
]


def _eye(n: int) -> NDArray:
    return NDArray.from_numpy(np.eye(n))


@schema("Imu", 1)
class Imu(Message, kw_only=True):
    """One IMU sample in the body FLU frame (`header.frame_id`, e.g. "base_link").

    Replaces sensor_msgs/Imu and px4 SensorCombined (fmu/out/sensor_combined, sensors/imu).
    Covariances are 3x3, None when unknown. `orientation` is meaningful only when
    `has_orientation` (many IMUs give rates and accelerations only).
    """

    header: Header = msgspec.field(default_factory=Header)
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)
    has_orientation: bool = False
    angular_velocity_radps: Vector3 = msgspec.field(default_factory=Vector3)
    linear_acceleration_mps2: Vector3 = msgspec.field(default_factory=Vector3)
    orientation_covariance: NDArray | None = None
    angular_velocity_covariance: NDArray | None = None
    linear_acceleration_covariance: NDArray | None = None

    __shapes__ = {
        "orientation_covariance": (3, 3),
        "angular_velocity_covariance": (3, 3),
        "linear_acceleration_covariance": (3, 3),
    }


# encoding -> (dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    "mono8": ("uint8", 1),
    "mono16": ("uint16", 1),
    "rgb8": ("uint8", 3),
    "bgr8": ("uint8", 3),
    "rgba8": ("uint8", 4),
    "bgra8": ("uint8", 4),
    "16UC1": ("uint16", 1),
    "32FC1": ("float32", 1),
}


@schema("Image", 1)
class Image(Message, kw_only=True):
    """A raw image: `data` is (height, width, channels), or (height, width) for one channel.

    Encodings: mono8, mono16, rgb8, bgr8, rgba8, bgra8, 16UC1, 32FC1 (Image.ENCODINGS).
    Replaces sensor_msgs/Image. Width, height, step and the data's shape/dtype are checked against
    `encoding` on decode, so `to_numpy()` always gives the advertised picture (zero-copy view).
    `step` (bytes per row) is kept for ROS parity; 0 on construction means "compute it".
    """

    header: Header = msgspec.field(default_factory=Header)
    height: int = 0
    width: int = 0
    encoding: str = "rgb8"
    step: int = 0
    data: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((0, 0, 3), "uint8"))

    ENCODINGS = IMAGE_ENCODINGS

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("encoding", self.encoding, IMAGE_ENCODINGS)
        dtype, channels = IMAGE_ENCODINGS[self.encoding]
        check_dtype("data", self.data, (dtype,))
        shape = list(self.data.shape)
        ok_shapes = [[self.height, self.width, channels]]
        if channels == 1:
            ok_shapes.append([self.height, self.width])
        if shape not in ok_shapes:
            raise ValueError(
                f"field `data` has shape {shape} but height={self.height}, width={self.width}, "
                f"encoding={self.encoding} needs {ok_shapes[-1]}"
            )
        row = self.width * channels * np.dtype(dtype).itemsize
        if self.step == 0:
            self.step = row
        elif self.step != row:
            raise ValueError(f"field `step` is {self.step} but a {self.encoding} row of width {self.width} is {row} bytes")

    @classmethod
    def from_numpy(cls, pixels: Any, encoding: str = "rgb8", header: Header | None = None) -> "Image":
        a = np.asarray(pixels)
        return cls(
            header=header or Header(), height=int(a.shape[0]), width=int(a.shape[1]),
            encoding=encoding, data=NDArray.from_numpy(a),
        )

    def to_numpy(self) -> np.ndarray:
        """Read-only (H, W[, C]) view of the pixels."""
        return self.data.to_numpy()


@schema("CameraInfo", 1)
class CameraInfo(Message, kw_only=True):
    """Pinhole calibration of one camera plus where it sits on the body.

    Replaces sensor_msgs/CameraInfo (K, D, R, P as in ROS, shaped as matrices) and adds the
    extrinsics `T_body_camera`: the camera (optical) frame's pose in the body FLU frame, so
    consumers need no separate TF tree.
    """

    header: Header = msgspec.field(default_factory=Header)
    width: int = 0
    height: int = 0
    distortion_model: str = "plumb_bob"
    K: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((3, 3)))
    D: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((5,)))
    R: NDArray = msgspec.field(default_factory=lambda: _eye(3))
    P: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((3, 4)))
    T_body_camera: Pose = msgspec.field(default_factory=Pose)

    __shapes__ = {"K": (3, 3), "D": (-1,), "R": (3, 3), "P": (3, 4)}

    @classmethod
    def pinhole(
        cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
        header: Header | None = None, T_body_camera: Pose | None = None,
    ) -> "CameraInfo":
        """An undistorted pinhole camera (what the simulator renders)."""
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        P = np.hstack([K, np.zeros((3, 1))])
        return cls(
            header=header or Header(), width=width, height=height, K=NDArray.from_numpy(K),
            P=NDArray.from_numpy(P), T_body_camera=T_body_camera or Pose(),
        )


@schema("PointCloud", 1)
class PointCloud(Message, kw_only=True):
    """N points (metres, float32 x/y/z rows) in `header.frame_id`, with optional per-point
    intensity (float32), labels (uint8, e.g. ground/obstacle/cluster id), ring (uint16, the
    laser's row, 0 = lowest beam) and time_offset_s (float32, when the point was measured, seconds
    after header.stamp_ns: a real sensor's sweep takes its whole period; the stamp is the sweep's
    first point).

    Replaces sensor_msgs/PointCloud2 with a fixed layout: consumers get an (N, 3) array directly.
    """

    header: Header = msgspec.field(default_factory=Header)
    points: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((0, 3), "float32"))
    intensity: NDArray | None = None
    labels: NDArray | None = None
    ring: NDArray | None = None
    time_offset_s: NDArray | None = None

    __shapes__ = {"points": (-1, 3), "intensity": (-1,), "labels": (-1,), "ring": (-1,), "time_offset_s": (-1,)}

    def __post_init__(self) -> None:
        super().__post_init__()
        check_dtype("points", self.points, ("float32",))
        check_dtype("intensity", self.intensity, ("float32",))
        check_dtype("labels", self.labels, ("uint8",))
        check_dtype("ring", self.ring, ("uint16",))
        check_dtype("time_offset_s", self.time_offset_s, ("float32",))
        n = self.points.shape[0]
        for name in ("intensity", "labels", "ring", "time_offset_s"):
            arr = getattr(self, name)
            if arr is not None and arr.shape[0] != n:
                raise ValueError(f"field `{name}` has {arr.shape[0]} entries but there are {n} points")

    @classmethod
    def from_numpy(cls, points: Any, intensity: Any = None, labels: Any = None,
                   header: Header | None = None) -> "PointCloud":
        return cls(
            header=header or Header(),
            points=NDArray.from_numpy(np.asarray(points, dtype=np.float32).reshape(-1, 3)),
            intensity=None if intensity is None else NDArray.from_numpy(intensity, "float32"),
            labels=None if labels is None else NDArray.from_numpy(labels, "uint8"),
        )

    def __len__(self) -> int:
        return self.points.shape[0]


@schema("OccupancyGrid", 1)
class OccupancyGrid(Message, kw_only=True):
    """A 2D costmap: `data[row, col]` (int8, height x width) is -1 unknown, 0 free .. 100 occupied.

    Replaces nav_msgs/OccupancyGrid. Cell (0, 0) has its corner at `origin` in `header.frame_id`
    (ENU); columns grow along the origin's x axis, rows along its y axis.
    """

    header: Header = msgspec.field(default_factory=Header)
    resolution_m: float = 0.1
    width: int = 0
    height: int = 0
    origin: Pose = msgspec.field(default_factory=Pose)
    data: NDArray = msgspec.field(default_factory=lambda: NDArray.zeros((0, 0), "int8"))

    UNKNOWN = -1
    FREE = 0
    OCCUPIED = 100

    __shapes__ = {"data": (-1, -1)}

    def __post_init__(self) -> None:
        super().__post_init__()
        check_dtype("data", self.data, ("int8",))
        if list(self.data.shape) != [self.height, self.width]:
            raise ValueError(f"field `data` has shape {list(self.data.shape)} but height x width is {[self.height, self.width]}")
        if not self.resolution_m > 0:
            raise ValueError(f"field `resolution_m` must be > 0, got {self.resolution_m!r}")


class Detection2D(msgspec.Struct, kw_only=True):
    """One detected object: axis-aligned box in pixels (centre + size), class and score (0..1)."""

    center_x_px: float = 0.0
    center_y_px: float = 0.0
    size_x_px: float = 0.0
    size_y_px: float = 0.0
    class_id: int = 0
    class_name: str = ""
    score: float = 0.0


@schema("Detection2DArray", 1)
class Detection2DArray(Message, kw_only=True):
    """Detections in one image; `header` is the image's (stamp and camera frame).

    Replaces vision_msgs/Detection2DArray (perception/detections).
    """

    header: Header = msgspec.field(default_factory=Header)
    detections: list[Detection2D] = []
    image_width: int = 0
    image_height: int = 0


@schema("BatteryState", 1)
class BatteryState(Message, kw_only=True):
    """Battery telemetry (fmu/out/battery_status). Replaces sensor_msgs/BatteryState and px4
    BatteryStatus. Unknown optional quantities are None, never a fake 0."""

    header: Header = msgspec.field(default_factory=Header)
    voltage_v: float = 0.0
    current_a: float | None = None
    remaining_fraction: float | None = None
    temperature_c: float | None = None
    cell_count: int = 0
    cell_voltages_v: list[float] = []
    time_remaining_s: float | None = None
    warning: int = 0

    # PX4 battery_status.warning
    WARNING_NONE = 0
    WARNING_LOW = 1
    WARNING_CRITICAL = 2
    WARNING_EMERGENCY = 3
    WARNING_FAILED = 4


@schema("DiagnosticStatus", 1)
class DiagnosticStatus(Message, kw_only=True):
    """Health of one service or component, published at 1 Hz on diagnostics/<service>.

    Replaces diagnostic_msgs/DiagnosticStatus; `values` is a map (not a key/value list) and also
    takes numbers and booleans so consumers need not parse strings.
    """

    header: Header = msgspec.field(default_factory=Header)
    level: int = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: dict[str, str | int | float | bool] = {}

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3

    @property
    def level_name(self) -> str:
        return enum_names(type(self)).get(self.level, str(self.level))


@schema("DiagnosticArray", 1)
class DiagnosticArray(Message, kw_only=True):
    """Many statuses at once: diagnostics/agg, the aggregator's roll-up."""

    header: Header = msgspec.field(default_factory=Header)
    status: list[DiagnosticStatus] = []


@schema("Odometry", 1)
class Odometry(Message, kw_only=True):
    """Estimated pose and velocity with 6x6 covariances (state/visual_odometry,
    fmu/in/vehicle_visual_odometry).

    Replaces nav_msgs/Odometry, px4 VehicleOdometry and the pose part of VIO-7's output. `pose` is
    `child_frame_id` (body FLU, "base_link") in `header.frame_id` (ENU, "odom"); `twist` is
    expressed in the child (body FLU) frame, as in ROS. Covariance order: x, y, z, roll, pitch, yaw
    (resp. vx, vy, vz, wx, wy, wz); None when the estimator has none.

    `reset_counter` goes up by one each time the estimator restarts (its pose may jump there), so a
    consumer re-aligns to the new pose instead of taking the jump for motion (MAVLink ODOMETRY's
    reset_counter). `quality_pct`: the estimator's own tracking quality, 1 (worst) - 100 (best);
    None when it gives none.
    """

    header: Header = msgspec.field(default_factory=Header)
    child_frame_id: str = "base_link"
    pose: Pose = msgspec.field(default_factory=Pose)
    twist: Twist = msgspec.field(default_factory=Twist)
    pose_covariance: NDArray | None = None
    twist_covariance: NDArray | None = None
    reset_counter: int = 0
    quality_pct: int | None = None

    __shapes__ = {"pose_covariance": (6, 6), "twist_covariance": (6, 6)}

    def __post_init__(self) -> None:
        super().__post_init__()
        check_dtype("pose_covariance", self.pose_covariance, ("float64", "float32"))
        check_dtype("twist_covariance", self.twist_covariance, ("float64", "float32"))
        if self.reset_counter < 0:
            raise ValueError(f"field `reset_counter` must be >= 0, got {self.reset_counter}")
        if self.quality_pct is not None and not 1 <= self.quality_pct <= 100:
            raise ValueError(f"field `quality_pct` must be 1-100 or None, got {self.quality_pct}")


@schema("VioHealth", 1)
class VioHealth(Message, kw_only=True):
    """State of the visual-inertial odometry (state/vio_health, 1 Hz and on change).

    VIO-1's health plus the non-pose parts of VIO-7's output (IMU bias, feature quality), so the
    perception coordinator and logs see why VIO is degraded.
    """

    header: Header = msgspec.field(default_factory=Header)
    state: int = 0
    message: str = ""
    strategy: str = ""
    tracked_features: int = 0
    lost_features: int = 0
    consecutive_lost: int = 0
    mean_parallax_px: float = 0.0
    mean_reprojection_error_px: float = 0.0
    accel_bias_mps2: Vector3 = msgspec.field(default_factory=Vector3)
    gyro_bias_radps: Vector3 = msgspec.field(default_factory=Vector3)
    bias_norm: float = 0.0

    INIT = 0
    TRACKING = 1
    DEGRADED = 2
    LOST = 3

    @property
    def state_name(self) -> str:
        return enum_names(type(self)).get(self.state, str(self.state))


@schema("PerceptionHealth", 1)
class PerceptionHealth(Message, kw_only=True):
    """The perception coordinator's verdict (perception/health, 1 Hz + on change): the single
    input the mission manager gates EXECUTING on. `overall_healthy` is vio_status == HEALTHY (true
    in a stack without VIO: nothing gates on it there).
    `lidar_status` (same enum; the LiDAR obstacle service's diagnostics) is reported, not gated on."""

    header: Header = msgspec.field(default_factory=Header)
    vio_status: int = 0
    detector_status: int = 0
    lidar_status: int = 0
    overall_healthy: bool = False
    message: str = ""

    UNKNOWN = 0
    INITIALIZING = 1
    HEALTHY = 2
    DEGRADED = 3
    FAILED = 4
    NOT_CONFIGURED = 5   # the stack runs no such source (e.g. `aero up --sensors camera`: no LiDAR)

    @classmethod
    def status_name(cls, value: int) -> str:
        return enum_names(cls).get(value, str(value))
