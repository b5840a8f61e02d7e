"""Quaternion and rotation algebra, frame-agnostic: (w, x, y, z), Hamilton, q rotates child-frame
vectors into the parent frame (R(q) @ v_child = v_parent).

One home for this maths: the MAVLink frame conversions (services/mavlink/frames), the simulated
vehicle's physics and the sensor models all use it. Functions take one quaternion/vector or
stacks ([..., 4] / [..., 3]); single values take a float fast path (the physics calls these at
hundreds of Hz).
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.schemas.geometry import euler_from_wxyz

__all__ = [
    "quat_multiply", "quat_conjugate", "quat_normalize", "quat_rotate", "quat_to_rotmat",
    "quat_from_rotmat", "quat_from_euler", "quat_to_euler", "quat_from_axis_angle", "quat_to_rotvec",
]


def _vec(v) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape[-1] != 3:
        raise ValueError(f"expected [..., 3] vectors, got shape {a.shape}")
    return a


def _quat(q) -> np.ndarray:
    a = np.asarray(q, dtype=float)
    if a.shape[-1] != 4:
        raise ValueError(f"expected [..., 4] (w, x, y, z) quaternions, got shape {a.shape}")
    return a


# ---------------------------------------------------------------------------------------------
# Quaternion algebra (w, x, y, z). Used by the conversions below and by the simulated vehicle.

def _components(a: np.ndarray):
    # Views, not copies: much cheaper than moveaxis/unstack.
    return a[..., 0], a[..., 1], a[..., 2], a[..., 3]


def _assemble(parts, shape) -> np.ndarray:
    out = np.empty(shape + (len(parts),))
    for i, part in enumerate(parts):
        out[..., i] = part
    return out


# The formulas below work on floats and on arrays alike; single quaternions take the float path
# (tolist), which is several times faster than numpy on 0-d values. The physics calls these at
# hundreds of Hz.

def _mul(w1, x1, y1, z1, w2, x2, y2, z2):
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def _rotmat(w, x, y, z):
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


# Single values as tuples of floats: the fast paths below, and what the simulated vehicle's step
# (400 Hz, services/sim/vehicle/floats.py) calls directly.

def mul_floats(a, b) -> tuple[float, float, float, float]:
    """Hamilton product a * b of two (w, x, y, z) tuples."""
    return _mul(*a, *b)


def normalize_floats(q) -> tuple[float, float, float, float]:
    """Unit norm with w >= 0, of a (w, x, y, z) tuple."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = -n if w < 0.0 else n
    return (w / n, x / n, y / n, z / n)


def rotvec_floats(q) -> tuple[float, float, float]:
    """Rotation vector of a (w, x, y, z) tuple, normalised first."""
    w, x, y, z = normalize_floats(q)
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if s < 1e-9 else 2.0 * math.atan2(s, w) / s
    return (x * k, y * k, z * k)


def axis_angle_floats(v) -> tuple[float, float, float, float]:
    """Quaternion of a rotation vector (x, y, z) tuple; sin(a/2)/a by its series near 0."""
    x, y, z = v
    angle = math.sqrt(x * x + y * y + z * z)
    k = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), x * k, y * k, z * k)


def quat_multiply(q1, q2) -> np.ndarray:
    """Hamilton product q1 * q2 (apply q2 first, then q1)."""
    a, b = _quat(q1), _quat(q2)
    if a.ndim == 1 and b.ndim == 1:
        return np.array(mul_floats(a.tolist(), b.tolist()))
    return _assemble(_mul(*_components(a), *_components(b)), np.broadcast_shapes(a.shape[:-1], b.shape[:-1]))


_CONJ = np.array([1.0, -1.0, -1.0, -1.0])


def quat_conjugate(q) -> np.ndarray:
    """Inverse of a unit quaternion."""
    return _quat(q) * _CONJ


def quat_normalize(q) -> np.ndarray:
    """Unit norm with w >= 0 (q and -q are the same rotation; a canonical sign makes outputs
    comparable and messages stable)."""
    a = _quat(q)
    if a.ndim == 1:
        return np.array(normalize_floats(a.tolist()))
    n = np.sqrt(np.sum(a * a, axis=-1, keepdims=True))
    return a / np.where(a[..., :1] < 0.0, -n, n)


def quat_to_rotmat(q) -> np.ndarray:
    """[..., 3, 3] rotation matrix R with R @ v_body = v_world."""
    a = quat_normalize(q)
    if a.ndim == 1:
        return np.array(_rotmat(*a.tolist()))
    rows = _rotmat(*_components(a))
    R = np.empty(a.shape[:-1] + (3, 3))
    for i in range(3):
        for j in range(3):
            R[..., i, j] = rows[i][j]
    return R


def quat_from_rotmat(R) -> np.ndarray:
    """Unit quaternion (w >= 0) of a single 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=float).tolist()
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    return quat_normalize(np.array(q))


def quat_rotate(q, v) -> np.ndarray:
    """R(q) @ v: a body vector expressed in the world frame."""
    R = quat_to_rotmat(q)
    return np.einsum("...ij,...j->...i", R, _vec(v))


def quat_from_euler(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """Intrinsic Z-Y-X (yaw, pitch, roll) angles -> quaternion. Frame-agnostic: the same formula
    serves NED/FRD (PX4 Euler angles) and ENU/FLU (ROS RPY)."""
    r, p, y = (np.asarray(v, dtype=float) * 0.5 for v in (roll_rad, pitch_rad, yaw_rad))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return _assemble((
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ), np.broadcast_shapes(r.shape, p.shape, y.shape))


def quat_to_euler(q) -> np.ndarray:
    """[..., 3] (roll, pitch, yaw) radians, intrinsic Z-Y-X; inverse of quat_from_euler."""
    a = quat_normalize(q)
    if a.ndim == 1:
        return np.array(euler_from_wxyz(*a.tolist()))
    return _assemble(euler_from_wxyz(*_components(a)), a.shape[:-1])


def quat_from_axis_angle(rotvec) -> np.ndarray:
    """Quaternion of a rotation vector (axis * angle, radians)."""
    v = _vec(rotvec)
    if v.ndim == 1:
        return np.array(axis_angle_floats(v.tolist()))
    angle = np.sqrt(np.sum(v * v, axis=-1, keepdims=True))
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps small rotations exact.
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), v * k], axis=-1)


def quat_to_rotvec(q) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a quaternion."""
    a = _quat(q)
    if a.ndim == 1:
        return np.array(rotvec_floats(a.tolist()))
    a = quat_normalize(a)
    w, xyz = a[..., :1], a[..., 1:]
    s = np.sqrt(np.sum(xyz * xyz, axis=-1, keepdims=True))
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-9
    k = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return xyz * k
