"""NED/FRD <-> ENU/FLU conversions: hand-worked cases first, then seeded property checks."""
import math

import numpy as np
import pytest

from aeroperception.services.mavlink import frames as f
from aeroperception.services.lib.geo import MapProjection

RNG_SEED = 20240607


def random_quats(n, rng):
    return f.quat_normalize(rng.normal(size=(n, 4)))


def same_rotation(q1, q2, atol=1e-9):
    """q and -q are the same rotation."""
    q1, q2 = np.asarray(q1), np.asarray(q2)
    return np.allclose(q1, q2, atol=atol) or np.allclose(q1, -q2, atol=atol)


# ------------------------------------------------------------------ positions and body vectors

def test_point_ned_to_enu_by_hand():
    np.testing.assert_allclose(f.ned_to_enu([1.0, 2.0, -3.0]), [2.0, 1.0, 3.0])
    np.testing.assert_allclose(f.enu_to_ned([2.0, 1.0, 3.0]), [1.0, 2.0, -3.0])


def test_vectors_are_vectorised():
    v = np.arange(12.0).reshape(4, 3)
    out = f.ned_to_enu(v)
    assert out.shape == (4, 3)
    np.testing.assert_allclose(out[1], [4.0, 3.0, -5.0])


def test_body_rates_frd_to_flu():
    # rolling right (p>0 FRD) is rolling right in FLU too (+x); pitch-up (q>0 FRD) is -y in FLU;
    # yawing right (r>0 FRD, clockwise seen from above) is -z in FLU.
    np.testing.assert_allclose(f.frd_to_flu([0.1, 0.2, 0.3]), [0.1, -0.2, -0.3])
    np.testing.assert_allclose(f.flu_to_frd([0.1, -0.2, -0.3]), [0.1, 0.2, 0.3])


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        f.ned_to_enu([1.0, 2.0])
    with pytest.raises(ValueError):
        f.q_ned_frd_to_enu_flu([1.0, 0.0, 0.0])


def test_static_rotations_are_proper():
    assert np.linalg.det(f.R_ENU_NED) == pytest.approx(1.0)
    assert np.linalg.det(f.R_FLU_FRD) == pytest.approx(1.0)
    np.testing.assert_allclose(f.quat_to_rotmat(f.Q_ENU_NED), f.R_ENU_NED, atol=1e-12)
    np.testing.assert_allclose(f.quat_to_rotmat(f.Q_FLU_FRD), f.R_FLU_FRD, atol=1e-12)


# ------------------------------------------------------------------ yaw

@pytest.mark.parametrize("yaw_ned, yaw_enu", [
    (0.0, math.pi / 2),            # facing North
    (math.pi / 2, 0.0),            # facing East
    (math.pi, -math.pi / 2),       # facing South
    (-math.pi / 2, -math.pi),      # facing West (wrapped into [-pi, pi))
    (math.radians(30), math.radians(60)),
])
def test_yaw_by_hand(yaw_ned, yaw_enu):
    assert f.wrap_pi(f.yaw_ned_to_enu(yaw_ned) - yaw_enu) == pytest.approx(0.0, abs=1e-12)
    assert f.wrap_pi(f.yaw_enu_to_ned(yaw_enu) - yaw_ned) == pytest.approx(0.0, abs=1e-12)


def test_yaw_is_float_for_scalars_and_array_for_arrays():
    assert isinstance(f.yaw_ned_to_enu(0.3), float)
    out = f.yaw_ned_to_enu(np.array([0.0, math.pi / 2]))
    np.testing.assert_allclose(out, [math.pi / 2, 0.0], atol=1e-12)


# ------------------------------------------------------------------ attitude

def test_level_heading_north():
    q_ned = f.quat_from_euler(0.0, 0.0, 0.0)  # PX4: level, nose North
    q_enu = f.q_ned_frd_to_enu_flu(q_ned)
    assert f.yaw_from_q(q_enu) == pytest.approx(math.pi / 2)
    # the nose (FLU +x) points North (ENU +y)
    np.testing.assert_allclose(f.quat_rotate(q_enu, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)


def test_level_heading_east_is_identity():
    q_enu = f.q_ned_frd_to_enu_flu(f.quat_from_euler(0.0, 0.0, math.pi / 2))
    assert same_rotation(q_enu, [1.0, 0.0, 0.0, 0.0])


def test_pitch_up():
    # PX4 pitch +10 deg is nose up; in ROS RPY (FLU) nose up is a negative pitch about +y (Left).
    q_enu = f.q_ned_frd_to_enu_flu(f.quat_from_euler(0.0, math.radians(10), 0.0))
    roll, pitch, yaw = f.euler_from_q(q_enu)
    assert roll == pytest.approx(0.0, abs=1e-12)
    assert pitch == pytest.approx(-math.radians(10))
    assert yaw == pytest.approx(math.pi / 2)
    nose = f.quat_rotate(q_enu, [1.0, 0.0, 0.0])
    assert nose[2] == pytest.approx(math.sin(math.radians(10)))  # nose above the horizon
    assert nose[1] > 0.9  # still facing North


def test_roll_right():
    # PX4 roll +20 deg: right wing down. In FLU that is +roll about x (left wing up).
    q_enu = f.q_ned_frd_to_enu_flu(f.quat_from_euler(math.radians(20), 0.0, 0.0))
    roll, pitch, _ = f.euler_from_q(q_enu)
    assert roll == pytest.approx(math.radians(20))
    assert pitch == pytest.approx(0.0, abs=1e-12)
    left_wing = f.quat_rotate(q_enu, [0.0, 1.0, 0.0])  # FLU +y
    assert left_wing[2] == pytest.approx(math.sin(math.radians(20)))  # left wing up


def test_attitude_agrees_with_vector_conversions():
    """Rotating an FRD vector with PX4's q then converting NED->ENU equals converting FRD->FLU
    then rotating with our q: the definition of a correct attitude conversion."""
    rng = np.random.default_rng(RNG_SEED)
    q_ned = random_quats(200, rng)
    v_frd = rng.normal(size=(200, 3))
    lhs = f.ned_to_enu(f.quat_rotate(q_ned, v_frd))
    rhs = f.quat_rotate(f.q_ned_frd_to_enu_flu(q_ned), f.frd_to_flu(v_frd))
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_attitude_round_trip():
    rng = np.random.default_rng(RNG_SEED + 1)
    q = random_quats(500, rng)
    back = f.q_ned_frd_to_enu_flu(f.q_enu_flu_to_ned_frd(q))
    np.testing.assert_allclose(back, f.quat_normalize(q), atol=1e-12)
    back = f.q_enu_flu_to_ned_frd(f.q_ned_frd_to_enu_flu(q))
    np.testing.assert_allclose(back, f.quat_normalize(q), atol=1e-12)


def test_yaw_from_attitude_matches_yaw_conversion():
    rng = np.random.default_rng(RNG_SEED + 2)
    for yaw_ned in rng.uniform(-math.pi, math.pi, size=50):
        roll, pitch = rng.uniform(-0.5, 0.5, size=2)
        q_enu = f.q_ned_frd_to_enu_flu(f.quat_from_euler(roll, pitch, yaw_ned))
        assert f.wrap_pi(f.yaw_from_q(q_enu) - f.yaw_ned_to_enu(yaw_ned)) == pytest.approx(0.0, abs=1e-9)


def test_vector_round_trips():
    rng = np.random.default_rng(RNG_SEED + 3)
    v = rng.normal(size=(100, 3))
    np.testing.assert_allclose(f.enu_to_ned(f.ned_to_enu(v)), v)
    np.testing.assert_allclose(f.flu_to_frd(f.frd_to_flu(v)), v)


# ------------------------------------------------------------------ quaternion helpers

def test_euler_round_trip_and_rotmat():
    rng = np.random.default_rng(RNG_SEED + 4)
    rpy = np.column_stack([rng.uniform(-3, 3, 100), rng.uniform(-1.5, 1.5, 100), rng.uniform(-3, 3, 100)])
    q = f.quat_from_euler(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(f.quat_to_euler(q), rpy, atol=1e-9)
    for qi in q[:10]:
        assert same_rotation(f.quat_from_rotmat(f.quat_to_rotmat(qi)), f.quat_normalize(qi))


def test_axis_angle_round_trip():
    rng = np.random.default_rng(RNG_SEED + 5)
    rv = rng.normal(size=(100, 3))
    rv *= (rng.uniform(0, 3.0, size=(100, 1)) / np.linalg.norm(rv, axis=1, keepdims=True))
    np.testing.assert_allclose(f.quat_to_rotvec(f.quat_from_axis_angle(rv)), rv, atol=1e-9)
    np.testing.assert_allclose(f.quat_from_axis_angle([0.0, 0.0, 0.0]), [1.0, 0.0, 0.0, 0.0])


def test_multiply_composes_rotations():
    rng = np.random.default_rng(RNG_SEED + 6)
    a, b = random_quats(20, rng), random_quats(20, rng)
    v = rng.normal(size=(20, 3))
    np.testing.assert_allclose(f.quat_rotate(f.quat_multiply(a, b), v),
                               f.quat_rotate(a, f.quat_rotate(b, v)), atol=1e-12)


# ------------------------------------------------------------------ covariances

def test_pose_covariance_by_hand():
    cov_ned = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    cov_ned[0, 2] = cov_ned[2, 0] = 0.5  # north-down correlation
    out = f.cov6_ned_frd_to_enu_flu(cov_ned)
    np.testing.assert_allclose(np.diag(out), [2.0, 1.0, 3.0, 0.1, 0.2, 0.3])
    assert out[1, 2] == pytest.approx(-0.5)  # north-up correlation: down flipped to up


def test_covariance_round_trips_and_urt():
    rng = np.random.default_rng(RNG_SEED + 7)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    np.testing.assert_allclose(f.cov6_enu_flu_to_ned_frd(f.cov6_ned_frd_to_enu_flu(cov)), cov, atol=1e-12)
    np.testing.assert_allclose(f.cov6_flu_to_frd(f.cov6_frd_to_flu(cov)), cov, atol=1e-12)
    urt = f.cov6_to_urt21(cov)
    assert len(urt) == 21
    np.testing.assert_allclose(f.urt21_to_cov6(urt), cov)


def test_twist_covariance_matches_vector_transform():
    """Cov of transformed samples == transformed cov (it is a linear map)."""
    rng = np.random.default_rng(RNG_SEED + 8)
    A = rng.normal(size=(6, 6))
    samples = rng.normal(size=(20000, 6)) @ A.T
    flu = np.concatenate([f.frd_to_flu(samples[:, :3]), f.frd_to_flu(samples[:, 3:])], axis=1)
    np.testing.assert_allclose(np.cov(flu.T), f.cov6_frd_to_flu(np.cov(samples.T)), atol=1e-9)


# ------------------------------------------------------------------ geodesy

def test_map_projection_round_trip():
    proj = MapProjection(47.397742, 8.545594)
    assert proj.reproject(0.0, 0.0) == (47.397742, 8.545594)
    lat, lon = proj.reproject(111.2, 0.0)  # ~0.001 deg of latitude per 111 m
    assert lat - 47.397742 == pytest.approx(0.001, rel=2e-3)
    assert lon == pytest.approx(8.545594, abs=1e-12)
    rng = np.random.default_rng(RNG_SEED + 9)
    for n, e in rng.uniform(-3000, 3000, size=(20, 2)):
        np.testing.assert_allclose(proj.project(*proj.reproject(n, e)), (n, e), atol=1e-6)
