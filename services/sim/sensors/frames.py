"""Small rotation helpers shared by the sensor models.

Conventions (ARCHITECTURE.md §2): world ENU, body FLU, quaternions (w, x, y, z) where
q_enu_flu rotates body vectors into the world (v_world = R(q) @ v_body). Camera optical frames
follow OpenCV/ROS: x right, y down, z forward.
"""
from __future__ import annotations

import numpy as np

from aeroperception.services.lib.optical import R_FLU_OPTICAL_FORWARD  # noqa: F401 - the sensors' name for it
from aeroperception.services.runtime.rotations import quat_from_rotmat, quat_to_rotmat


# One home for quaternion maths: these are the runtime's, under the names the sensor code uses.
quat_to_rot = quat_to_rotmat
rot_to_quat = quat_from_rotmat


def rot_x(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_rot(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Z-Y-X (yaw, then pitch, then roll) rotation, the aerospace/ROS convention."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def pose_of(truth_or_pose) -> tuple[np.ndarray, np.ndarray]:
    """(position_enu_m, R_enu_flu) from a VehicleTruth or a (position, q_wxyz) pair, so the
    renderers accept either without depending on the dynamics code."""
    if isinstance(truth_or_pose, tuple):
        pos, q = truth_or_pose
    else:
        pos, q = truth_or_pose.position_enu_m, truth_or_pose.q_enu_flu
    return np.asarray(pos, dtype=float), quat_to_rot(q)
