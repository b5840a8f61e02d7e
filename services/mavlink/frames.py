"""The one NED/FRD <-> ENU/FLU conversion module.

Only the MAVLink boundaries import this: fmu, gcs and sim (the simulated vehicle speaks NED on
its MAVLink side, like PX4). Everything else in the stack is ENU world / FLU body, so a frame
bug can only live here, where it is tested.

Conventions
- World: NED (x North, y East, z Down) <-> ENU (x East, y North, z Up).
- Body: FRD (x Forward, y Right, z Down) <-> FLU (x Forward, y Left, z Up).
- Quaternions are (w, x, y, z), Hamilton, and rotate body vectors into the world frame:
  PX4's attitude q is world NED <- body FRD; ours is world ENU <- body FLU.
- Yaw: NED heading is 0 facing North, clockwise positive; ENU yaw is 0 facing East,
  counter-clockwise positive, so yaw_enu = pi/2 - yaw_ned.

Functions take a single vector/quaternion or stacks of them ([..., 3] / [..., 4]) and return
numpy float arrays; conversions are their own inverses where the maths says so (positions,
body rates), and a named inverse is still provided so call sites read in one direction.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "R_ENU_NED", "R_FLU_FRD", "Q_ENU_NED", "Q_FLU_FRD",
    "ned_to_enu", "enu_to_ned", "frd_to_flu", "flu_to_frd",
    "q_ned_frd_to_enu_flu", "q_enu_flu_to_ned_frd",
    "yaw_ned_to_enu", "yaw_enu_to_ned", "yaw_rate_ned_to_enu", "yaw_rate_enu_to_ned", "wrap_pi",
    "yaw_from_q", "euler_from_q",
    "cov6_ned_frd_to_enu_flu", "cov6_enu_flu_to_ned_frd", "cov6_frd_to_flu", "cov6_flu_to_frd",
    "urt21_to_cov6", "cov6_to_urt21",
    "quat_multiply", "quat_conjugate", "quat_normalize", "quat_rotate", "quat_to_rotmat",
    "quat_from_rotmat", "quat_from_euler", "quat_to_euler", "quat_from_axis_angle",
    "quat_to_rotvec",
]

# v_enu = R_ENU_NED @ v_ned: swap x/y, negate z. A proper rotation (det +1): 180 deg about (1,1,0).
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# v_flu = R_FLU_FRD @ v_frd: 180 deg about x.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])
_S = math.sqrt(0.5)
Q_ENU_NED = np.array([0.0, _S, _S, 0.0])
Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])
_FLIP_Z = np.array([1.0, 1.0, -1.0])
_FLIP_YZ = np.array([1.0, -1.0, -1.0])


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


def quat_multiply(q1, q2) -> np.ndarray:
    """Hamilton product q1 * q2 (apply q2 first, then q1)."""
    a, b = _quat(q1), _quat(q2)
    if a.ndim == 1 and b.ndim == 1:
        return np.array(_mul(*a.tolist(), *b.tolist()))
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
        w, x, y, z = a.tolist()
        n = math.sqrt(w * w + x * x + y * y + z * z)
        n = -n if w < 0.0 else n
        return np.array((w / n, x / n, y / n, z / n))
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
        w, x, y, z = a.tolist()
        return np.array((math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                         math.asin(min(max(2 * (w * y - z * x), -1.0), 1.0)),
                         math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))))
    w, x, y, z = _components(a)
    return _assemble((
        np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
        np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)),
        np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
    ), a.shape[:-1])


def quat_from_axis_angle(rotvec) -> np.ndarray:
    """Quaternion of a rotation vector (axis * angle, radians)."""
    v = _vec(rotvec)
    if v.ndim == 1:
        x, y, z = v.tolist()
        angle = math.sqrt(x * x + y * y + z * z)
        k = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
        return np.array((math.cos(0.5 * angle), x * k, y * k, z * k))
    angle = np.sqrt(np.sum(v * v, axis=-1, keepdims=True))
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps small rotations exact.
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), v * k], axis=-1)


def quat_to_rotvec(q) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a quaternion."""
    a = quat_normalize(q)
    if a.ndim == 1:
        w, x, y, z = a.tolist()
        s = math.sqrt(x * x + y * y + z * z)
        k = 2.0 if s < 1e-9 else 2.0 * math.atan2(s, w) / s
        return np.array((x * k, y * k, z * k))
    w, xyz = a[..., :1], a[..., 1:]
    s = np.sqrt(np.sum(xyz * xyz, axis=-1, keepdims=True))
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-9
    k = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return xyz * k


# ---------------------------------------------------------------------------------------------
# Vectors and positions

def ned_to_enu(v_ned) -> np.ndarray:
    """World position/velocity/acceleration NED -> ENU: (x, y, z) -> (y, x, -z)."""
    return _vec(v_ned)[..., [1, 0, 2]] * _FLIP_Z



def enu_to_ned(v_enu) -> np.ndarray:
    """World vector ENU -> NED (the same swap; named for readable call sites)."""
    return ned_to_enu(v_enu)


def frd_to_flu(v_frd) -> np.ndarray:
    """Body vector (rates, specific force, body velocity) FRD -> FLU: (x, y, z) -> (x, -y, -z)."""
    return _vec(v_frd) * _FLIP_YZ



def flu_to_frd(v_flu) -> np.ndarray:
    """Body vector FLU -> FRD."""
    return frd_to_flu(v_flu)


# ---------------------------------------------------------------------------------------------
# Attitude

def q_ned_frd_to_enu_flu(q_ned_frd) -> np.ndarray:
    """PX4 attitude (NED <- FRD) -> ours (ENU <- FLU): q_enu_flu = Q_ENU_NED * q_ned_frd * Q_FRD_FLU."""
    q = quat_multiply(quat_multiply(Q_ENU_NED, _quat(q_ned_frd)), quat_conjugate(Q_FLU_FRD))
    return quat_normalize(q)


def q_enu_flu_to_ned_frd(q_enu_flu) -> np.ndarray:
    """Ours (ENU <- FLU) -> PX4 attitude (NED <- FRD): q_ned_frd = Q_NED_ENU * q_enu_flu * Q_FLU_FRD."""
    q = quat_multiply(quat_multiply(quat_conjugate(Q_ENU_NED), _quat(q_enu_flu)), Q_FLU_FRD)
    return quat_normalize(q)


def euler_from_q(q_enu_flu) -> tuple[float, float, float]:
    """(roll, pitch, yaw) radians of one ENU <- FLU attitude: ROS RPY, yaw 0 = East, CCW."""
    r, p, y = quat_to_euler(q_enu_flu)
    return float(r), float(p), float(y)


def yaw_from_q(q_enu_flu) -> float:
    """ENU yaw (0 = facing East, counter-clockwise positive) of one ENU <- FLU attitude."""
    return euler_from_q(q_enu_flu)[2]


def wrap_pi(angle_rad):
    """Wrap to [-pi, pi); a float for a scalar, an array for an array."""
    out = (np.asarray(angle_rad, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi
    return float(out) if out.ndim == 0 else out


def yaw_ned_to_enu(yaw_ned_rad):
    """Heading (0 = North, clockwise) -> ENU yaw (0 = East, counter-clockwise), wrapped."""
    return wrap_pi(math.pi / 2 - np.asarray(yaw_ned_rad, dtype=float))


def yaw_enu_to_ned(yaw_enu_rad):
    """ENU yaw -> NED heading (the same reflection about 45 deg), wrapped."""
    return yaw_ned_to_enu(yaw_enu_rad)


def yaw_rate_ned_to_enu(yaw_rate_ned_radps):
    """Heading rate (clockwise positive, about Down) -> ENU yaw rate (counter-clockwise, about Up)."""
    return -yaw_rate_ned_radps


def yaw_rate_enu_to_ned(yaw_rate_enu_radps):
    return -yaw_rate_enu_radps


# ---------------------------------------------------------------------------------------------
# Covariances (odometry): 6x6 over (x, y, z, roll, pitch, yaw) for the pose and
# (vx, vy, vz, wx, wy, wz) for the twist, as MAVLink ODOMETRY and our Odometry state them.
# The pose block's position part is in the world frame; its attitude part is small rotations
# about the body axes (roll/pitch/yaw), so it changes with the body convention, not the world one:
# a pitch variance stays a pitch variance. Hence T = blkdiag(R_world, R_body).

def _cov6_transform(cov, R_top: np.ndarray, R_bottom: np.ndarray) -> np.ndarray:
    c = np.asarray(cov, dtype=float)
    if c.shape[-2:] != (6, 6):
        raise ValueError(f"expected [..., 6, 6] covariances, got shape {c.shape}")
    T = np.zeros((6, 6))
    T[:3, :3] = R_top
    T[3:, 3:] = R_bottom
    return T @ c @ T.T


def cov6_ned_frd_to_enu_flu(cov) -> np.ndarray:
    """Pose covariance: position NED -> ENU, attitude FRD -> FLU."""
    return _cov6_transform(cov, R_ENU_NED, R_FLU_FRD)


def cov6_enu_flu_to_ned_frd(cov) -> np.ndarray:
    """Pose covariance: position ENU -> NED, attitude FLU -> FRD."""
    return _cov6_transform(cov, R_ENU_NED.T, R_FLU_FRD.T)


def cov6_frd_to_flu(cov) -> np.ndarray:
    """Body-frame twist covariance FRD -> FLU."""
    return _cov6_transform(cov, R_FLU_FRD, R_FLU_FRD)


def cov6_flu_to_frd(cov) -> np.ndarray:
    """Body-frame twist covariance FLU -> FRD."""
    return _cov6_transform(cov, R_FLU_FRD.T, R_FLU_FRD.T)


_IU = np.triu_indices(6)


def urt21_to_cov6(urt) -> np.ndarray:
    """MAVLink's 21-float upper-right triangle (row-major) -> symmetric 6x6. A NaN first element
    means "unknown" in MAVLink; the NaNs are kept for the caller to test."""
    a = np.asarray(urt, dtype=float).reshape(21)
    c = np.zeros((6, 6))
    c[_IU] = a
    return c + np.triu(c, 1).T


def cov6_to_urt21(cov) -> list[float]:
    """Symmetric 6x6 -> MAVLink's 21-float upper-right triangle (row-major)."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise ValueError(f"expected a 6x6 covariance, got shape {c.shape}")
    return [float(x) for x in c[_IU]]
