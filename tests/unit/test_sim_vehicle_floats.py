"""The vehicle step's plain-float maths (services/sim/vehicle/floats.py) gives what runtime/rotations
gives through numpy: the physics moved to floats for CPU, not to other numbers."""
from __future__ import annotations

import math

import numpy as np

from aeroperception.services.mavlink.frames import yaw_from_q
from aeroperception.services.runtime import rotations as rot
from aeroperception.services.sim.vehicle import floats as fl


def test_float_quaternion_maths_matches_rotations():
    rng = np.random.default_rng(4)
    for _ in range(200):
        a, b = rng.standard_normal(4), rng.standard_normal(4)
        v = rng.standard_normal(3) * rng.choice([1e-8, 1e-3, 1.0])   # tiny rotations take the series
        qa, qb = fl.floats(a), fl.floats(b)
        assert fl.quat_mul(qa, qb) == fl.floats(rot.quat_multiply(a, b))
        assert fl.quat_conj(qa) == fl.floats(rot.quat_conjugate(a))
        assert fl.quat_normalize(qa) == fl.floats(rot.quat_normalize(a))
        assert fl.quat_to_rotvec(qa) == fl.floats(rot.quat_to_rotvec(a))
        assert fl.quat_from_axis_angle(fl.floats(v)) == fl.floats(rot.quat_from_axis_angle(v))
        assert fl.body_z(qa) == fl.floats(rot.quat_to_rotmat(a)[:, 2])
        assert math.isclose(fl.yaw_of(qa), yaw_from_q(a), rel_tol=0, abs_tol=1e-15)   # atan2: math vs numpy


def test_or_zero_and_clip():
    assert [fl.or_zero(v) for v in (math.nan, math.inf, -math.inf, -2.5)] == [0.0, 0.0, 0.0, -2.5]
    assert (fl.clip(5.0, -1.0, 2.0), fl.clip(-5.0, -1.0, 2.0), fl.clip(0.5, -1.0, 2.0)) == (2.0, -1.0, 0.5)
