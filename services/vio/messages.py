"""Conversions between the Zenoh schemas and the VIO's own types (plain functions, no I/O)."""
from __future__ import annotations

import numpy as np

from aeroperception.schemas import (
    Header, Image, Imu, NDArray, Odometry, Pose, Quaternion, Twist, Vector3, VioHealth,
    VioResetRequest,
)
from aeroperception.services.runtime.rotations import quat_from_rotmat, quat_to_rotmat

from .dto import FeatureQuality, ImuBias, ImuSample, StrategyHealth, VioOutput, WarmStartPose

ODOM_FRAME = "odom"
BODY_FRAME = "base_link"


def imu_sample(msg: Imu) -> ImuSample:
    return ImuSample(int(msg.header.stamp_ns), msg.angular_velocity_radps.to_array(),
                     msg.linear_acceleration_mps2.to_array())


def odometry(out: VioOutput) -> Odometry:
    """state/visual_odometry: pose of base_link in odom, twist in base_link (FLU), covariances
    in (x, y, z, roll, pitch, yaw) / (vx, vy, vz, wx, wy, wz) order."""
    T = out.world_T_body
    R = T[:3, :3]
    return Odometry(
        header=Header(stamp_ns=int(out.stamp_ns), frame_id=ODOM_FRAME), child_frame_id=BODY_FRAME,
        pose=Pose(position=Vector3.from_array(T[:3, 3]), orientation=Quaternion.from_array(quat_from_rotmat(R))),
        twist=Twist(linear=Vector3.from_array(R.T @ out.velocity_world_mps),
                    angular=Vector3.from_array(out.angular_velocity_body_radps)),
        pose_covariance=NDArray.from_numpy(np.ascontiguousarray(out.pose_covariance_6x6, np.float64)),
        twist_covariance=NDArray.from_numpy(np.ascontiguousarray(out.twist_covariance_6x6, np.float64)),
        reset_counter=out.reset_counter, quality_pct=out.quality_pct)


def health(snapshot: StrategyHealth, strategy: str, stamp_ns: int, quality: FeatureQuality | None,
           bias: ImuBias | None) -> VioHealth:
    q = quality or FeatureQuality()
    b = bias or ImuBias()
    return VioHealth(
        header=Header(stamp_ns=int(stamp_ns), frame_id=ODOM_FRAME), state=snapshot.state,
        message=snapshot.message, strategy=strategy, tracked_features=q.tracked, lost_features=q.lost,
        consecutive_lost=snapshot.consecutive_lost, mean_parallax_px=q.mean_parallax_px,
        mean_reprojection_error_px=q.mean_reprojection_error_px,
        accel_bias_mps2=Vector3.from_array(b.accel_mps2), gyro_bias_radps=Vector3.from_array(b.gyro_radps),
        bias_norm=snapshot.bias_norm)


def pixels(msg: Image) -> np.ndarray:
    """(H, W) or (H, W, C) view of an image message."""
    return msg.to_numpy()


def warm_start(req: VioResetRequest) -> WarmStartPose:
    """vio/srv/reset's pose -> the strategy's warm start; ValueError naming what is wrong."""
    p, q = req.pose.position.to_array(), req.pose.orientation.to_array()
    v = req.velocity_mps.to_array()
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
        raise ValueError("pose and velocity must be finite")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 0.01:
        raise ValueError(f"orientation must be a unit quaternion (norm {n:.3f})")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rotmat(q / n), p
    return WarmStartPose(T, v)
