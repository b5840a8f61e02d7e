"""VIO back end on a simulated IMU with known biases: the smoother recovers them, and the shared
preintegration helper integrates a known trajectory exactly."""
import numpy as np
import pytest

from aeroperception.services.runtime.rotations import quat_to_rotmat
from aeroperception.services.sim.sensors.imu import ImuModel
from aeroperception.services.sim.world.scenario import ImuConfig
from aeroperception.services.vio.backend import Backend, BackendConfig, tangent_to_world_cov
from aeroperception.services.vio.dto import ImuBias, ImuSample
from aeroperception.services.vio.imu import ImuNoise, ImuPreintegrator, gravity_aligned_rotation
from aeroperception.tools.bench.vio import orbit_from_rest

GYRO_BIAS = np.array([0.01, -0.02, 0.015])
ACCEL_BIAS = np.array([0.12, -0.08, 0.1])


def pose(tr) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rotmat(tr.q_enu_flu), tr.position_enu_m
    return T


def imu_stream(duration_s: float, noiseless: bool, rate_hz: float = 200.0):
    cfg = ImuConfig(initial_gyro_bias_radps=tuple(GYRO_BIAS), initial_accel_bias_mps2=tuple(ACCEL_BIAS),
                    noiseless=noiseless, gyro_random_walk=0.0, accel_random_walk=0.0)
    model = ImuModel(cfg, seed=3)
    dt = int(1e9 / rate_hz)
    truth = lambda t: orbit_from_rest(t, (0.0, 0.0, 3.0), 6.0, 12.0, still_s=0.5, ramp_s=1.5)
    out = []
    for t in range(0, int(duration_s * 1e9) + dt, dt):
        s = model.sample(truth(t), dt_s=dt * 1e-9)
        out.append(ImuSample(t, s.angular_velocity_flu_radps, s.linear_acceleration_flu_mps2))
    return out, truth


def test_preintegration_of_noiseless_imu_reproduces_the_trajectory():
    samples, truth = imu_stream(4.0, noiseless=True)
    pre = ImuPreintegrator(ImuNoise())
    t0, t1 = int(2.0e9), int(3.0e9)
    T, v = pre.predict(pre.integrate(samples, t0, t1), pose(truth(t0)), truth(t0).velocity_enu_mps, ImuBias())
    assert np.linalg.norm(T[:3, 3] - truth(t1).position_enu_m) < 0.01
    assert np.linalg.norm(v - truth(t1).velocity_enu_mps) < 0.02
    # A bias is subtracted from every sample: an accel bias b shifts 1 s of motion by ~b/2.
    b = ImuBias(np.array([0.2, 0.0, 0.0]), np.zeros(3))
    Tb, _ = pre.predict(pre.integrate(samples, t0, t1, b), pose(truth(t0)), truth(t0).velocity_enu_mps, b)
    assert 0.07 < np.linalg.norm(Tb[:3, 3] - T[:3, 3]) < 0.13


def test_gravity_alignment_maps_specific_force_to_up():
    R = gravity_aligned_rotation(np.array([9.0, 0.5, -3.7]))
    up = R @ np.array([9.0, 0.5, -3.7])
    assert np.allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    with pytest.raises(ValueError):
        gravity_aligned_rotation(np.zeros(3))


def test_smoother_recovers_known_imu_biases_from_visual_relative_poses():
    samples, truth = imu_stream(12.0, noiseless=False)
    rng = np.random.default_rng(1)
    be = Backend(ImuNoise(gyro_random_walk=1e-5, accel_random_walk=1e-4), BackendConfig(lag_s=2.0))
    still = [s for s in samples if s.t_ns <= int(0.4e9)]
    t0 = int(0.4e9)
    T0 = np.eye(4)
    T0[:3, :3] = gravity_aligned_rotation(np.mean([s.accel_mps2 for s in still], axis=0),
                                          yaw_rad=np.arctan2(pose(truth(t0))[1, 0], pose(truth(t0))[0, 0]))
    T0[:3, 3] = truth(t0).position_enu_m
    be.initialize(t0, T0, np.zeros(3), ImuBias())   # biases unknown at start
    kf_t = t0
    cov = np.diag([9e-6] * 6)     # 0.17 deg, 3 mm: what the stereo front end reports
    for k in range(1, 116):
        t = t0 + k * int(0.1e9)
        T_rel = np.linalg.inv(pose(truth(kf_t))) @ pose(truth(t))
        noise = rng.normal(0, 3e-3, 6)
        import gtsam
        T_meas = (gtsam.Pose3(T_rel) * gtsam.Pose3.Expmap(noise)).matrix()
        est = be.add_frame(t, samples, (kf_t, T_meas, cov))
        if k % 4 == 0:
            kf_t = t
    assert np.linalg.norm(est.bias.gyro_radps - GYRO_BIAS) < 4e-3, est.bias
    assert np.linalg.norm(est.bias.accel_mps2 - ACCEL_BIAS) < 0.05, est.bias
    # The reported covariance is a proper one, and rotating it to the world keeps it so.
    C = tangent_to_world_cov(est.world_T_body, est.pose_cov_tangent)
    assert np.allclose(C, C.T, atol=1e-12) and np.all(np.linalg.eigvalsh(C) > 0)


def test_fixed_lag_window_stays_bounded_over_a_long_flight():
    """Cost per frame stays flat: the smoother holds only lag_s of states however long it runs (the
    state count is the proof; the per-frame time is `aero bench vio`'s, not a timed test's)."""
    samples, truth = imu_stream(31.0, noiseless=True)
    be = Backend(ImuNoise(), BackendConfig(lag_s=1.0))
    t0 = int(0.4e9)
    be.initialize(t0, pose(truth(t0)), np.zeros(3), ImuBias())
    sizes, kf_t = [], t0
    for k in range(1, 601):                   # 30 s at 20 Hz
        t = t0 + k * 50_000_000
        T_rel = np.linalg.inv(pose(truth(kf_t))) @ pose(truth(t))
        be.add_frame(t, samples, (kf_t, T_rel, np.diag([1e-5] * 6)))
        sizes.append(be.smoother.calculateEstimate().size())
        if k % 8 == 0:
            kf_t = t
    assert max(sizes) <= 3 * (20 + 3)         # X, V, B per frame over 1 s at 20 Hz
    assert sizes[-1] == sizes[300]
    est = be.last
    assert np.linalg.norm(est.world_T_body[:3, 3] - truth(t).position_enu_m) < 0.05


def test_window_covariance_is_recomputed_every_nth_visual_frame_and_on_every_frame_without_a_fix():
    """The marginal (ISAM2 walks the Bayes tree after each update: the back end's dearest step after the
    update itself) is kept for covariance_every_frames - 1 frames while visual fixes go on; a frame
    without one grows the covariance, so it is always recomputed, and so is the next one. Estimates
    are the same as with every frame's marginal; the kept covariances equal a fresh one within 15 %."""
    samples, truth = imu_stream(4.0, noiseless=True)
    t0 = int(0.4e9)
    runs = {}
    for n in (1, 2):
        be = Backend(ImuNoise(), BackendConfig(lag_s=1.0, covariance_every_frames=n))
        be.initialize(t0, pose(truth(t0)), np.zeros(3), ImuBias())
        out = []
        for k in range(1, 41):
            t = t0 + k * 50_000_000
            T_rel = np.linalg.inv(pose(truth(t0 + (k // 8) * 400_000_000))) @ pose(truth(t))
            visual = None if k in (20, 21) else (t0 + (k // 8) * 400_000_000, T_rel, np.diag([1e-5] * 6))
            out.append((be.add_frame(t, samples, visual), be.covariance_age))
        runs[n] = out
    every, alternate = runs[1], runs[2]
    assert all(np.array_equal(a.world_T_body, b.world_T_body) for (a, _), (b, _) in zip(every, alternate))
    ages = [age for _, age in alternate]
    assert ages[19] == 0 and ages[20] == 0 and ages[21] == 0      # frames 20, 21 without a fix, 22 after them
    assert ages.count(1) >= 12 and max(ages) == 1
    for (a, _), (b, age) in zip(every, alternate):
        sa, sb = np.sqrt(np.diag(a.pose_cov_tangent)), np.sqrt(np.diag(b.pose_cov_tangent))
        assert np.allclose(sa, sb, rtol=1e-9) if age == 0 else np.allclose(sa, sb, rtol=0.15)
