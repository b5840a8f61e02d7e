"""ROS 2 sensor messages -> our sensors/** (the other direction of convert.py). Plain functions, no
Zenoh: a vendor's ROS 2 driver (camera, IMU, LiDAR) on rmw_zenoh feeds the stack through the bridge.

Frames: ROS body frames are FLU (REP-103) as ours are, so an Imu is taken as it is; a frame_id
with REP-103's `_ned` / `_frd` suffix is refused, never silently flipped. Camera images stay in the
camera's optical frame; where the camera sits on the body is not in a CameraInfo, so the bridge's
`<side>_mount_*` parameters give T_body_camera. Clouds stay in the sensor frame (the lidar
service's mount_* place it on the body).

Every function raises ValueError for a message it cannot convert (the bridge counts and drops it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from aeroperception.schemas import CameraInfo, Header, Image, Imu, NDArray, Pose, Quaternion, Vector3
from aeroperception.services.runtime.rotations import quat_from_rotmat

from . import pointcloud2

IMAGE, COMPRESSED, INFO, IMU, CLOUD = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                                       "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/Imu",
                                       "sensor_msgs/msg/PointCloud2")
# Raw encodings taken: ROS name -> (numpy dtype, channels); the same names as ours.
RAW_ENCODINGS = {"mono8": ("u1", 1), "mono16": ("u2", 1), "rgb8": ("u1", 3), "bgr8": ("u1", 3)}
COMPRESSED_FORMATS = ("jpeg", "jpg", "png")
NED_SUFFIXES = ("_ned", "_frd")


def header(ros_header: Any) -> Header:
    """Stamp (sec, nanosec) -> stamp_ns; frame_id kept."""
    return Header(stamp_ns=int(ros_header.stamp.sec) * 1_000_000_000 + int(ros_header.stamp.nanosec),
                  frame_id=ros_header.frame_id)


def image(msg: Any) -> Image:
    """sensor_msgs/Image (mono8, mono16, rgb8, bgr8; rows padded to `step`; big-endian mono16)."""
    if msg.encoding not in RAW_ENCODINGS:
        raise ValueError(f"Image encoding {msg.encoding!r} is not taken (taken: {', '.join(RAW_ENCODINGS)})")
    code, channels = RAW_ENCODINGS[msg.encoding]
    dtype = np.dtype((">" if msg.is_bigendian else "<") + code)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, np.uint8).reshape(-1)
    if step < row or data.size < (h - 1) * step + row:
        raise ValueError(f"Image {w}x{h} {msg.encoding}: step {step} and {data.size} bytes of data are too short")
    rows = np.lib.stride_tricks.as_strided(data, (h, row), (step, 1)) if h else np.zeros((0, row), np.uint8)
    pixels = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="), copy=False)
    shape = (h, w) if channels == 1 else (h, w, channels)
    return Image.from_numpy(pixels.reshape(shape), msg.encoding, header(msg.header))


def compressed_image(msg: Any) -> Image:
    """sensor_msgs/CompressedImage in JPEG or PNG (image_transport's `compressed`: format
    "<encoding>; jpeg compressed <encoding>" or just "jpeg"): mono8 / mono16 / bgr8 as decoded."""
    import cv2

    fmt = msg.format.lower()
    if not any(f in fmt for f in COMPRESSED_FORMATS) or "compresseddepth" in fmt.replace(" ", ""):
        raise ValueError(f"CompressedImage format {msg.format!r} is not taken (jpeg or png)")
    pixels = cv2.imdecode(np.asarray(msg.data, np.uint8).reshape(-1), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise ValueError(f"CompressedImage ({msg.format}) does not decode")
    if pixels.ndim == 2:
        enc = {np.dtype(np.uint8): "mono8", np.dtype(np.uint16): "mono16"}.get(pixels.dtype)
    else:
        enc = "bgr8" if pixels.dtype == np.uint8 and pixels.shape[2] == 3 else None
    if enc is None:
        raise ValueError(f"CompressedImage decodes to {pixels.dtype} x {pixels.shape[2:] or 1} channels: not taken")
    return Image.from_numpy(pixels, enc, header(msg.header))


def camera_info(msg: Any, t_body_camera: np.ndarray) -> CameraInfo:
    """sensor_msgs/CameraInfo (plumb_bob; K, D, R, P) with T_body_camera (4x4, body FLU <- optical)."""
    if msg.distortion_model != "plumb_bob":
        raise ValueError(f"CameraInfo distortion model {msg.distortion_model!r} is not taken (plumb_bob)")
    K = np.asarray(msg.k, np.float64).reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or msg.width <= 0 or msg.height <= 0:
        raise ValueError(f"CameraInfo {msg.width}x{msg.height} with fx {K[0, 0]}, fy {K[1, 1]}: not a calibrated camera")
    return CameraInfo(header=header(msg.header), width=int(msg.width), height=int(msg.height),
                      distortion_model="plumb_bob", K=NDArray.from_numpy(K),
                      D=NDArray.from_numpy(np.asarray(msg.d, np.float64).reshape(-1)),
                      R=NDArray.from_numpy(np.asarray(msg.r, np.float64).reshape(3, 3)),
                      P=NDArray.from_numpy(np.asarray(msg.p, np.float64).reshape(3, 4)),
                      T_body_camera=Pose(position=Vector3.from_array(t_body_camera[:3, 3]),
                                         orientation=Quaternion.from_array(quat_from_rotmat(t_body_camera[:3, :3]))))


def _covariance(values: Any) -> NDArray | None:
    """ROS's 9 values -> 3x3, None when unknown (all zeros) or "no estimate" (first = -1)."""
    c = np.asarray(values, np.float64).reshape(3, 3)
    return None if c[0, 0] == -1.0 or not c.any() else NDArray.from_numpy(c)


def imu(msg: Any) -> Imu:
    """sensor_msgs/Imu in a FLU body frame (REP-103); orientation only when it has an estimate."""
    frame = msg.header.frame_id.lower()
    if frame.endswith(NED_SUFFIXES):
        raise ValueError(f"Imu frame {msg.header.frame_id!r} is NED/FRD (REP-103 suffix): the stack takes FLU")
    w, a, q = msg.angular_velocity, msg.linear_acceleration, msg.orientation
    values = (w.x, w.y, w.z, a.x, a.y, a.z)
    if not np.isfinite(values).all():
        raise ValueError("Imu has a non-finite rate or acceleration")
    has_q = float(msg.orientation_covariance[0]) != -1.0 and (q.x, q.y, q.z, q.w) != (0.0, 0.0, 0.0, 0.0)
    return Imu(header=header(msg.header), has_orientation=has_q,
               orientation=Quaternion(w=float(q.w), x=float(q.x), y=float(q.y), z=float(q.z)) if has_q else Quaternion(),
               angular_velocity_radps=Vector3(x=float(w.x), y=float(w.y), z=float(w.z)),
               linear_acceleration_mps2=Vector3(x=float(a.x), y=float(a.y), z=float(a.z)),
               orientation_covariance=_covariance(msg.orientation_covariance) if has_q else None,
               angular_velocity_covariance=_covariance(msg.angular_velocity_covariance),
               linear_acceleration_covariance=_covariance(msg.linear_acceleration_covariance))


def point_cloud(msg: Any):
    return pointcloud2.point_cloud(msg, header(msg.header))


@dataclass(frozen=True)
class Source:
    """One configured ROS topic feeding one of our keys."""

    topic: str          # fully qualified ROS name
    key: str
    ros_type: str

    def converter(self, mounts: dict[str, np.ndarray]) -> Callable[[Any], Any]:
        if self.ros_type == INFO:
            t = mounts[self.key.split("/")[2]]
            return lambda m: camera_info(m, t)
        return {IMAGE: image, COMPRESSED: compressed_image, IMU: imu, CLOUD: point_cloud}[self.ros_type]


def ros_type_for(key: str, topic: str) -> str:
    """The ROS type a key is fed by; an image key's topic ending in `/compressed` (image_transport's
    name) is a CompressedImage. ValueError for a key the bridge cannot feed."""
    if key.startswith("sensors/camera/") and key.endswith("/image"):
        return COMPRESSED if topic.rstrip("/").endswith("/compressed") else IMAGE
    types = {"sensors/imu": IMU, "sensors/lidar/points": CLOUD}
    if key.startswith("sensors/camera/") and key.endswith("/info"):
        return INFO
    if key in types:
        return types[key]
    raise ValueError(f"{key} cannot be fed from ROS")
