"""Plain-float maths for the vehicle's physics and control step (400 Hz in the stack).

Why: numpy costs ~0.5-1 us per call on a 3-element array, and a hovering step made ~150 such calls
(a tenth of that as float arithmetic). The vehicle's state stays numpy where others read it
(RigidBodyState, Setpoint, AttitudeThrust, VehicleTruth): a step converts in with `floats` and out
with `array`, here and nowhere else, and works on tuples in between.

3-vectors are (x, y, z), quaternions (w, x, y, z) Hamilton, as in runtime/rotations; the quaternion
functions are its single-value formulas (its `_mul`, and the same operations in the same order as
its float paths), so a step gives the same floats it gave through numpy.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.services.runtime.rotations import _mul

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def floats(a: np.ndarray) -> tuple[float, ...]:
    """numpy vector -> tuple of Python floats (the step's way in)."""
    return tuple(a.tolist())


def array(v) -> np.ndarray:
    """Tuple of floats -> numpy vector (the step's way out)."""
    return np.array(v)


def or_zero(v: float) -> float:
    """NaN ("not controlled", a setpoint's convention) or infinity -> 0."""
    return v if math.isfinite(v) else 0.0


def clip(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a * b (apply b first)."""
    return _mul(*a, *b)


def quat_conj(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def quat_normalize(q: Quat) -> Quat:
    """Unit norm with w >= 0, as rotations.quat_normalize."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = -n if w < 0.0 else n
    return (w / n, x / n, y / n, z / n)


def quat_to_rotvec(q: Quat) -> Vec3:
    """Rotation vector (axis * angle) of q, normalised first, as rotations.quat_to_rotvec."""
    w, x, y, z = quat_normalize(q)
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if s < 1e-9 else 2.0 * math.atan2(s, w) / s
    return (x * k, y * k, z * k)


def quat_from_axis_angle(v: Vec3) -> Quat:
    """Quaternion of a rotation vector, as rotations.quat_from_axis_angle."""
    x, y, z = v
    angle = math.sqrt(x * x + y * y + z * z)
    k = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), x * k, y * k, z * k)


def body_z(q: Quat) -> Vec3:
    """The body's +z axis in the parent frame: R(q)'s third column (q normalised first)."""
    w, x, y, z = quat_normalize(q)
    return (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))


def yaw_of(q: Quat) -> float:
    """Yaw (Z-Y-X) of q, as frames.yaw_from_q: the yaw line of schemas.geometry.euler_from_wxyz
    (which computes all three angles with numpy, ~4 us on floats)."""
    w, x, y, z = quat_normalize(q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
