"""Our schemas <-> standard ROS 2 messages (rosbags dataclasses). Plain functions, no Zenoh.

Frames stay as they are on Zenoh (ENU world, FLU body) because those are ROS's own conventions
(REP-103/105). ROS wants Odometry's twist in the child (body) frame: VehicleState's world-ENU
velocity is rotated into FLU here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from aeroperception.schemas import (
    Detection2DArray, GoToPositionGoal, Image, Imu, Odometry, PointCloud, Vector3, VehicleState,
)
from aeroperception.services.runtime.rotations import quat_conjugate, quat_rotate, quat_to_euler

# Frames a goal may be given in: the stack's local ENU world.
GOAL_FRAMES = ("", "map", "odom", "world", "enu")


class Converter:
    """Builds ROS messages of one typestore."""

    def __init__(self, store):
        self.store = store
        self.T = store.types

    # ------------------------------------------------------------ building blocks

    def header(self, stamp_ns: int, frame_id: str):
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.T["std_msgs/msg/Header"](stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                             frame_id=frame_id)

    def vector3(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q):
        return self.T["geometry_msgs/msg/Quaternion"](x=float(q.x), y=float(q.y), z=float(q.z), w=float(q.w))

    def pose(self, position, orientation):
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=float(position.x), y=float(position.y), z=float(position.z)),
            orientation=self.quaternion(orientation))

    @staticmethod
    def covariance(arr, n: int) -> np.ndarray:
        """Row-major n*n float64, a copy the caller may write (decoded arrays are read-only views);
        all zeros when unknown (ROS: "covariance unknown")."""
        if arr is None:
            return np.zeros(n * n, dtype=np.float64)
        return np.array(arr.to_numpy() if hasattr(arr, "to_numpy") else arr, dtype=np.float64).reshape(n * n)

    def odometry(self, stamp_ns, frame_id, child_frame_id, position, orientation, linear_body, angular_body,
                 pose_cov, twist_cov):
        T = self.T
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, frame_id), child_frame_id=child_frame_id,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(position, orientation),
                                                           covariance=self.covariance(pose_cov, 6)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=self.vector3(linear_body), angular=self.vector3(angular_body)),
                covariance=self.covariance(twist_cov, 6)))

    # ------------------------------------------------------------ ours -> ROS

    def from_vehicle_state(self, s: VehicleState):
        q = s.orientation
        qa = np.array([q.w, q.x, q.y, q.z])
        v_world = np.array([s.velocity_mps.x, s.velocity_mps.y, s.velocity_mps.z])
        v_body = quat_rotate(quat_conjugate(qa), v_world)
        w = s.angular_velocity_radps
        return self.odometry(s.header.stamp_ns, s.header.frame_id or "map", "base_link", s.position_m, q,
                             v_body, (w.x, w.y, w.z), s.pose_covariance, s.twist_covariance)

    def from_odometry(self, o: Odometry):
        lin, ang = o.twist.linear, o.twist.angular
        return self.odometry(o.header.stamp_ns, o.header.frame_id or "odom", o.child_frame_id, o.pose.position,
                             o.pose.orientation, (lin.x, lin.y, lin.z), (ang.x, ang.y, ang.z),
                             o.pose_covariance, o.twist_covariance)

    def from_imu(self, m: Imu):
        ocov = self.covariance(m.orientation_covariance, 3)
        if not m.has_orientation:
            ocov[0] = -1.0  # ROS: "no orientation estimate"
        w, a = m.angular_velocity_radps, m.linear_acceleration_mps2
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(m.header.stamp_ns, m.header.frame_id or "base_link"),
            orientation=self.quaternion(m.orientation), orientation_covariance=ocov,
            angular_velocity=self.vector3((w.x, w.y, w.z)),
            angular_velocity_covariance=self.covariance(m.angular_velocity_covariance, 3),
            linear_acceleration=self.vector3((a.x, a.y, a.z)),
            linear_acceleration_covariance=self.covariance(m.linear_acceleration_covariance, 3))

    def from_image(self, m: Image):
        data = np.ascontiguousarray(m.data.to_numpy())
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(m.header.stamp_ns, m.header.frame_id or "camera"), height=m.height, width=m.width,
            encoding=m.encoding, is_bigendian=0, step=m.step or (data.nbytes // max(m.height, 1)),
            data=data.view(np.uint8).reshape(-1))

    def from_point_cloud(self, m: PointCloud):
        T = self.T
        pts = np.asarray(m.points.to_numpy(), dtype=np.float32)
        cols = [pts]
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)  # 7 = FLOAT32
                  for i, n in enumerate("xyz")]
        if m.intensity is not None:
            cols.append(np.asarray(m.intensity.to_numpy(), dtype=np.float32).reshape(-1, 1))
            fields.append(T["sensor_msgs/msg/PointField"](name="intensity", offset=12, datatype=7, count=1))
        block = np.ascontiguousarray(np.hstack(cols) if len(cols) > 1 else pts)
        n = block.shape[0]
        return T["sensor_msgs/msg/PointCloud2"](
            header=self.header(m.header.stamp_ns, m.header.frame_id or "lidar"), height=1, width=n, fields=fields,
            is_bigendian=False, point_step=4 * block.shape[1], row_step=4 * block.shape[1] * n,
            data=block.view(np.uint8).reshape(-1), is_dense=bool(np.isfinite(pts).all()))

    def from_detections(self, m: Detection2DArray):
        T = self.T
        header = self.header(m.header.stamp_ns, m.header.frame_id or "camera")
        no_pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36, dtype=np.float64))
        dets = []
        for d in m.detections:
            hyp = T["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=d.class_name or str(d.class_id),
                                                                 score=float(d.score)),
                pose=no_pose)
            bbox = T["vision_msgs/msg/BoundingBox2D"](
                center=T["vision_msgs/msg/Pose2D"](position=T["vision_msgs/msg/Point2D"](x=float(d.center_x_px),
                                                                                        y=float(d.center_y_px)),
                                                   theta=0.0),
                size_x=float(d.size_x_px), size_y=float(d.size_y_px))
            dets.append(T["vision_msgs/msg/Detection2D"](header=header, results=[hyp], bbox=bbox, id=""))
        return T["vision_msgs/msg/Detection2DArray"](header=header, detections=dets)

    # ------------------------------------------------------------ ROS -> ours

    def goal_from_pose_stamped(self, msg: Any) -> GoToPositionGoal:
        """A goto goal from a ROS PoseStamped (ENU). Raises ValueError for a frame we do not fly
        in or a non-finite pose; the mission still applies its own checks (geofence, state)."""
        frame = msg.header.frame_id.strip("/").lower()
        if frame not in GOAL_FRAMES:
            raise ValueError(f"goal frame {msg.header.frame_id!r} is not the local ENU frame ({', '.join(GOAL_FRAMES[1:])})")
        p, q = msg.pose.position, msg.pose.orientation
        values = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("goal pose has a non-finite value")
        norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
        yaw = float(quat_to_euler(np.array([q.w, q.x, q.y, q.z]) / norm)[2]) if norm > 1e-6 else None
        return GoToPositionGoal(position_m=Vector3(x=float(p.x), y=float(p.y), z=float(p.z)), yaw_rad=yaw)


@dataclass(frozen=True)
class Bridged:
    """One of our keys as a ROS topic: schema in, ROS type and topic out, converter name."""

    key: str
    topic: str          # relative to the bridge's ROS namespace
    ros_type: str
    convert: str        # Converter method


# Every key the bridge can publish (the `topics` parameter picks a subset).
CATALOG: dict[str, Bridged] = {b.key: b for b in [
    Bridged("state/vehicle", "odom", "nav_msgs/msg/Odometry", "from_vehicle_state"),
    Bridged("state/visual_odometry", "vio/odom", "nav_msgs/msg/Odometry", "from_odometry"),
    Bridged("sensors/imu", "imu", "sensor_msgs/msg/Imu", "from_imu"),
    Bridged("sensors/camera/left/image", "camera/left/image_raw", "sensor_msgs/msg/Image", "from_image"),
    Bridged("sensors/camera/right/image", "camera/right/image_raw", "sensor_msgs/msg/Image", "from_image"),
    Bridged("sensors/lidar/points", "lidar/points", "sensor_msgs/msg/PointCloud2", "from_point_cloud"),
    Bridged("perception/obstacles", "perception/obstacles", "sensor_msgs/msg/PointCloud2", "from_point_cloud"),
    Bridged("perception/detections", "detections", "vision_msgs/msg/Detection2DArray", "from_detections"),
]}
GOAL_TYPE = "geometry_msgs/msg/PoseStamped"


def conversion(conv: Converter, b: Bridged) -> Callable[[Any], Any]:
    return getattr(conv, b.convert)
