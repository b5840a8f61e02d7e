"""Geometry value types shared by every message: Vector3, Quaternion, Pose, Twist, PoseStamped.

These are the one home for points, rotations and velocities; no other module defines its own.
The nested value types are plain Structs (not registered: they never travel alone); only
PoseStamped is a top-level message (mission/active_goal).

Frames: world/local quantities are ENU (x East, y North, z Up), body quantities FLU
(x Forward, y Left, z Up). A Quaternion used as an orientation rotates body-frame vectors into
the world frame (v_world = R(q) v_body), as in ROS. Nothing here ever holds NED/FRD.
"""
from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np

from ._base import Header, Message, schema

__all__ = ["Vector3", "Quaternion", "Pose", "Twist", "PoseStamped"]


class Vector3(msgspec.Struct, kw_only=True):
    """A 3-vector; its frame and unit are stated by the field that holds it (e.g. `velocity_mps`)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0

    @classmethod
    def from_array(cls, a: Any) -> "Vector3":
        x, y, z = np.asarray(a, dtype=float).reshape(3).tolist()   # floats; 6x faster than float() each
        return cls(x=x, y=y, z=z)

    def to_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z], dtype=float)


def euler_from_wxyz(w, x, y, z):
    """(roll, pitch, yaw) radians, intrinsic Z-Y-X, of unit quaternion components: floats or
    arrays alike. The one place this formula lives: Quaternion.to_euler/to_yaw (messages) and
    services/runtime/rotations.quat_to_euler (numpy stacks) both call it."""
    return (np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
            np.arcsin(np.minimum(np.maximum(2 * (w * y - z * x), -1.0), 1.0)),
            np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


class Quaternion(msgspec.Struct, kw_only=True):
    """Unit quaternion (w, x, y, z), Hamilton convention; default identity.

    As an orientation it rotates body (FLU) vectors into the world (ENU) frame.
    """

    w: float = 1.0
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0

    @classmethod
    def from_array(cls, a: Any) -> "Quaternion":
        """From a (w, x, y, z) array (the order used throughout the project)."""
        w, x, y, z = np.asarray(a, dtype=float).reshape(4).tolist()
        return cls(w=w, x=x, y=y, z=z)

    def to_array(self) -> np.ndarray:
        """As a (w, x, y, z) numpy array."""
        return np.array([self.w, self.x, self.y, self.z], dtype=float)

    @classmethod
    def from_euler(cls, roll_rad: float, pitch_rad: float, yaw_rad: float) -> "Quaternion":
        """From intrinsic Z-Y-X (yaw, then pitch, then roll) angles: ENU world <- FLU body."""
        cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
        cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
        cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
        return cls(
            w=cr * cp * cy + sr * sp * sy,
            x=sr * cp * cy - cr * sp * sy,
            y=cr * sp * cy + sr * cp * sy,
            z=cr * cp * sy - sr * sp * cy,
        )

    @classmethod
    def from_yaw(cls, yaw_rad: float) -> "Quaternion":
        """Level attitude with heading `yaw_rad` (ENU: 0 = facing East, counter-clockwise positive)."""
        return cls(w=math.cos(yaw_rad / 2), z=math.sin(yaw_rad / 2))

    def to_euler(self) -> tuple[float, float, float]:
        """(roll_rad, pitch_rad, yaw_rad), intrinsic Z-Y-X, the inverse of from_euler."""
        roll, pitch, yaw = euler_from_wxyz(self.w, self.x, self.y, self.z)
        return float(roll), float(pitch), float(yaw)

    def to_yaw(self) -> float:
        """Heading (ENU: 0 = facing East, counter-clockwise positive), the inverse of from_yaw."""
        return self.to_euler()[2]


class Pose(msgspec.Struct, kw_only=True):
    """Position (m) and orientation of a child frame in a parent frame (ENU world <- FLU body)."""

    position: Vector3 = msgspec.field(default_factory=Vector3)
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)


class Twist(msgspec.Struct, kw_only=True):
    """Linear (m/s) and angular (rad/s) velocity; the holder states the frame."""

    linear: Vector3 = msgspec.field(default_factory=Vector3)
    angular: Vector3 = msgspec.field(default_factory=Vector3)


@schema("PoseStamped", 1)
class PoseStamped(Message, kw_only=True):
    """A pose at a time in `header.frame_id` (ENU). The goal the mission hands the planner
    (mission/active_goal) and the waypoints of a Trajectory."""

    header: Header = msgspec.field(default_factory=Header)
    pose: Pose = msgspec.field(default_factory=Pose)
