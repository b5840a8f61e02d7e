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

from aeroperception.services.runtime.rotations import (  # noqa: E402 - re-exported for the sim
    _quat, _vec, quat_conjugate, quat_from_axis_angle, quat_from_euler,
    quat_from_rotmat, quat_multiply, quat_normalize, quat_rotate, quat_to_euler, quat_to_rotmat,
    quat_to_rotvec,
)


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
