"""Plain-float maths for the vehicle's physics and control step (400 Hz in the stack).

Why: numpy costs ~0.5-1 us per call on a 3-element array, and a hovering step made ~150 such calls
(a tenth of that as float arithmetic). The vehicle's state stays numpy where others read it
(RigidBodyState, Setpoint, AttitudeThrust, VehicleTruth): a step converts in with `floats` and out
with `array`, here and nowhere else, and works on tuples in between.

3-vectors are (x, y, z), quaternions (w, x, y, z) Hamilton, as in runtime/rotations, whose float
paths (its *_floats functions) are the quaternion maths here: a step gives the same floats it gave
through numpy.
"""
from __future__ import annotations

import math

import numpy as np

from aeroperception.services.runtime.rotations import (  # noqa: F401 - the step's quaternion maths, one home
    axis_angle_floats as quat_from_axis_angle, mul_floats as quat_mul, normalize_floats as quat_normalize,
    rotvec_floats as quat_to_rotvec,
)

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


def quat_conj(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def body_z(q: Quat) -> Vec3:
    """The body's +z axis in the parent frame: R(q)'s third column (q normalised first)."""
    w, x, y, z = quat_normalize(q)
    return (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))


def yaw_of(q: Quat) -> float:
    """Yaw (Z-Y-X) of q, as frames.yaw_from_q: the yaw line of schemas.geometry.euler_from_wxyz
    (which computes all three angles with numpy, ~4 us on floats)."""
    w, x, y, z = quat_normalize(q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
