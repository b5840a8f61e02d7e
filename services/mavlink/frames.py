"""The one NED/FRD <-> ENU/FLU conversion module (seed 000 §3). Only fmu, gcs and sim import it.

World: NED (x North, y East, z Down) <-> ENU (x East, y North, z Up): swap x/y, negate z.
Body:  FRD (x Forward, y Right, z Down) <-> FLU (x Forward, y Left, z Up): negate y and z.
Quaternions are (w, x, y, z), Hamilton, and rotate body vectors into the world frame:
  q_enu_flu = q_ENU_NED * q_ned_frd * q_FRD_FLU
Both fixed rotations are their own inverse, so the same formula converts back.
"""
from __future__ import annotations

import math

import numpy as np

_P = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])   # NED <-> ENU (symmetric, own inverse)
_B = np.diag([1.0, -1, -1])                            # FRD <-> FLU (own inverse)
_Q_ENU_NED = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])  # 180 deg about (1,1,0)/sqrt2
_Q_FRD_FLU = np.array([0.0, 1.0, 0.0, 0.0])                          # 180 deg about x


def ned_to_enu(v) -> np.ndarray:
    """Vector(s) (..., 3) from NED to ENU; also velocities and accelerations."""
    v = np.asarray(v, float)
    return v[..., [1, 0, 2]] * np.array([1.0, 1.0, -1.0])


enu_to_ned = ned_to_enu  # the same permutation both ways


def frd_to_flu(v) -> np.ndarray:
    """Body vector(s) (..., 3) from FRD to FLU (rates, specific force, body velocity)."""
    return np.asarray(v, float) * np.array([1.0, -1.0, -1.0])


flu_to_frd = frd_to_flu


def q_mul(a, b) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def _canonical(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def q_ned_frd_to_enu_flu(q_ned_frd) -> np.ndarray:
    """Attitude as PX4 reports it (FRD body -> NED world) to ours (FLU body -> ENU world)."""
    return _canonical(q_mul(q_mul(_Q_ENU_NED, np.asarray(q_ned_frd, float)), _Q_FRD_FLU))


q_enu_flu_to_ned_frd = q_ned_frd_to_enu_flu


def q_to_rot(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def euler_from_q(q) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad, ZYX convention, of a body->world quaternion."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def yaw_from_q(q) -> float:
    return euler_from_q(q)[2]


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """Heading clockwise from North -> counter-clockwise from East."""
    return wrap_pi(math.pi / 2 - yaw_ned_rad)


yaw_enu_to_ned = yaw_ned_to_enu


def cov6_enu_flu_to_ned_frd(cov) -> np.ndarray:
    """6x6 pose covariance [position (world), rotation (body)] between ENU/FLU and NED/FRD."""
    t = np.zeros((6, 6))
    t[:3, :3], t[3:, 3:] = _P, _B
    return t @ np.asarray(cov, float) @ t.T


cov6_ned_frd_to_enu_flu = cov6_enu_flu_to_ned_frd


def cov6_flu_to_frd(cov) -> np.ndarray:
    """6x6 twist covariance [linear, angular], both body frame."""
    t = np.zeros((6, 6))
    t[:3, :3], t[3:, 3:] = _B, _B
    return t @ np.asarray(cov, float) @ t.T


cov6_frd_to_flu = cov6_flu_to_frd
