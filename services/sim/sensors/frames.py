"""Small rotation helpers shared by the sensor models.

Conventions (ARCHITECTURE.md §2): world ENU, body FLU, quaternions (w, x, y, z) where
q_enu_flu rotates body vectors into the world (v_world = R(q) @ v_body). Camera optical frames
follow OpenCV/ROS: x right, y down, z forward.
"""
from __future__ import annotations

import numpy as np

# Optical frame axes expressed in the body (FLU) frame for a camera looking straight forward:
# optical x (right) = -body y, optical y (down) = -body z, optical z (forward) = +body x.
R_FLU_OPTICAL_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def quat_to_rot(q_wxyz) -> np.ndarray:
    """3x3 rotation matrix of a (w, x, y, z) quaternion (normalised here, so slightly
    denormalised integrator output is fine)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=float) / np.linalg.norm(q_wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion of a rotation matrix, w >= 0."""
    r = np.asarray(r, dtype=float)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


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


def yaw_quat(yaw_rad: float) -> np.ndarray:
    """(w, x, y, z) for a pure ENU yaw (0 = facing East, counter-clockwise positive)."""
    return np.array([np.cos(yaw_rad / 2), 0.0, 0.0, np.sin(yaw_rad / 2)])


def pose_of(truth_or_pose) -> tuple[np.ndarray, np.ndarray]:
    """(position_enu_m, R_enu_flu) from a VehicleTruth or a (position, q_wxyz) pair, so the
    renderers accept either without depending on the dynamics code."""
    if isinstance(truth_or_pose, tuple):
        pos, q = truth_or_pose
    else:
        pos, q = truth_or_pose.position_enu_m, truth_or_pose.q_enu_flu
    return np.asarray(pos, dtype=float), quat_to_rot(q)
