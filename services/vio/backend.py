"""Visual-inertial back end: a GTSAM incremental fixed-lag smoother over the last `lag_s` seconds
of frame states (pose X, velocity V, IMU bias B per frame).

Factors: one CombinedImuFactor between consecutive frames (preintegrated by imu.py, bias random
walk included), one BetweenFactorPose3 per visual fix (keyframe -> frame, body frame, covariance
from the front end), and priors at initialisation (gravity-aligned attitude, zero position, the
still vehicle's velocity and gyro bias). Old states are marginalised, so cost per frame stays
flat over a long flight (a plain ISAM2 grows without bound, the fixed-lag smoother does not).
ISAM2 runs with QR factorisation: Cholesky throws "indeterminate linear system" with realistic
bias noise.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from .dto import ImuBias, ImuSample
from .imu import ImuNoise, ImuPreintegrator, from_gtsam_bias, to_gtsam_bias


@dataclass
class BackendConfig:
    lag_s: float = 1.5
    init_rotation_sigma_rad: float = 0.01
    init_position_sigma_m: float = 0.001
    init_velocity_sigma_mps: float = 0.1
    init_accel_bias_sigma_mps2: float = 0.1
    init_gyro_bias_sigma_radps: float = 0.01
    # Started in motion (a hand-carried rig, a restart in flight): the specific force averaged for
    # gravity holds the motion's acceleration too (MH_01's start: 0.75 m/s^2 off g, a 4.2 deg tilt
    # error) and the mean gyro is the turn rate, not the bias. The roll / pitch prior and the gyro
    # bias prior widen to these (yaw stays init_rotation_sigma_rad: it is the odom frame's gauge).
    moving_init_tilt_sigma_rad: float = 0.1
    moving_init_gyro_bias_sigma_radps: float = 0.1
    compute_covariance: bool = True
    # The window marginal (0.9-1.5 ms CPU a frame: ISAM2 recomputes the marginals up the Bayes tree
    # after every update) is recomputed every this many frames while the visual fixes go on, and at
    # every frame without one (the covariance grows fast on the IMU alone); in between the last one
    # is kept (frame to frame its sigmas change 0.4 % median). 1 = every frame.
    covariance_every_frames: int = 2


@dataclass
class BackendEstimate:
    t_ns: int
    world_T_body: np.ndarray
    velocity_world_mps: np.ndarray
    bias: ImuBias
    pose_cov_tangent: np.ndarray      # 6x6, GTSAM Pose3 tangent (rotation, translation), body frame
    velocity_cov_world: np.ndarray    # 3x3
    bias_cov: np.ndarray              # 6x6 (accel, gyro)


class BackendError(RuntimeError):
    """The smoother failed (degenerate system); the caller re-initialises."""


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of T in GTSAM's (rotation, translation) tangent order."""
    return gtsam.Pose3(T).AdjointMap()


def tangent_to_world_cov(world_T_body: np.ndarray, cov_tangent: np.ndarray) -> np.ndarray:
    """Pose3 tangent covariance (rot, trans; right perturbation, body axes) -> world-aligned
    (x, y, z, roll, pitch, yaw) as Odometry carries it."""
    R = world_T_body[:3, :3]
    J = np.zeros((6, 6))
    J[0:3, 3:6] = R   # world position error = R * body translation perturbation
    J[3:6, 0:3] = R   # world-axis small rotation = R * body rotation perturbation
    return J @ cov_tangent @ J.T


class Backend:
    def __init__(self, noise: ImuNoise, cfg: BackendConfig | None = None):
        self.noise, self.cfg = noise, cfg or BackendConfig()
        self.preint = ImuPreintegrator(noise)
        self.reset()

    def reset(self) -> None:
        p = gtsam.ISAM2Params()
        p.setFactorization("QR")
        p.relinearizeSkip = 1
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.cfg.lag_s, p)
        self.index_of: dict[int, int] = {}   # frame stamp -> state index (inside the window)
        self.t0_ns: int | None = None
        self.i = -1
        self.last: BackendEstimate | None = None
        self.visual_skipped = 0
        self.covariance_age = 0          # frames since the window marginal was computed
        self.last_had_visual = False

    @property
    def initialized(self) -> bool:
        return self.last is not None

    def _stamp(self, t_ns: int) -> float:
        return (t_ns - self.t0_ns) * 1e-9

    def initialize(self, t_ns: int, world_T_body: np.ndarray, velocity_world_mps: np.ndarray,
                   bias: ImuBias, velocity_sigma_mps: float | None = None,
                   moving: bool = False) -> BackendEstimate:
        """Priors at the first state; velocity_sigma_mps overrides the config (unknown motion);
        moving: attitude (roll, pitch) and gyro bias are uncertain too (see BackendConfig)."""
        c = self.cfg
        self.reset()
        self.t0_ns, self.i = t_ns, 0
        g = gtsam.NonlinearFactorGraph()
        pose = gtsam.Pose3(world_T_body)
        g.add(gtsam.PriorFactorPose3(X(0), pose, gtsam.noiseModel.Gaussian.Covariance(
            self._pose_prior_cov(np.asarray(world_T_body, float)[:3, :3], moving))))
        g.add(gtsam.PriorFactorVector(V(0), np.asarray(velocity_world_mps, float),
                                      gtsam.noiseModel.Isotropic.Sigma(3, velocity_sigma_mps or c.init_velocity_sigma_mps)))
        gyro_sigma = c.moving_init_gyro_bias_sigma_radps if moving else c.init_gyro_bias_sigma_radps
        g.add(gtsam.PriorFactorConstantBias(B(0), to_gtsam_bias(bias), gtsam.noiseModel.Diagonal.Sigmas(
            np.r_[[c.init_accel_bias_sigma_mps2] * 3, [gyro_sigma] * 3])))
        v = gtsam.Values()
        v.insert(X(0), pose)
        v.insert(V(0), np.asarray(velocity_world_mps, float))
        v.insert(B(0), to_gtsam_bias(bias))
        self._update(g, v, t_ns)
        return self._estimate(t_ns)

    def _pose_prior_cov(self, R_world_body: np.ndarray, moving: bool) -> np.ndarray:
        """6x6 prior covariance in the Pose3 tangent (body rotation, body translation): roll and
        pitch about the world's horizontal axes, yaw about its vertical one, rotated into the body."""
        c = self.cfg
        tilt = c.moving_init_tilt_sigma_rad if moving else c.init_rotation_sigma_rad
        rot_world = np.diag([tilt ** 2, tilt ** 2, c.init_rotation_sigma_rad ** 2])
        cov = np.zeros((6, 6))
        cov[:3, :3] = R_world_body.T @ rot_world @ R_world_body
        cov[3:, 3:] = c.init_position_sigma_m ** 2 * np.eye(3)
        return cov

    def add_frame(self, t_ns: int, samples: list[ImuSample],
                  visual: tuple[int, np.ndarray, np.ndarray] | None = None) -> BackendEstimate:
        """New state at t_ns: IMU factor from the previous state, plus a visual factor
        (reference keyframe stamp, T_ref_cur in the body frame, 6x6 tangent covariance)."""
        if self.last is None:
            raise BackendError("back end not initialised")
        prev, i0 = self.last, self.i
        i1 = i0 + 1
        bias = to_gtsam_bias(prev.bias)
        pim = self.preint.integrate(samples, prev.t_ns, t_ns, bias)
        pred_T, pred_v = ImuPreintegrator.predict(pim, prev.world_T_body, prev.velocity_world_mps, bias)
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.CombinedImuFactor(X(i0), V(i0), X(i1), V(i1), B(i0), B(i1), pim))
        has_visual = False
        if visual is not None:
            ref_t, T_rel, cov = visual
            ref = self.index_of.get(ref_t)
            if ref is not None and self._stamp(t_ns) - self._stamp(ref_t) < 0.9 * self.cfg.lag_s:
                g.add(gtsam.BetweenFactorPose3(X(ref), X(i1), gtsam.Pose3(T_rel),
                                               gtsam.noiseModel.Gaussian.Covariance(cov)))
                has_visual = True
            else:
                self.visual_skipped += 1
        v = gtsam.Values()
        v.insert(X(i1), gtsam.Pose3(pred_T))
        v.insert(V(i1), pred_v)
        v.insert(B(i1), bias)
        self.i = i1
        self._update(g, v, t_ns)
        keep_cov = (has_visual and self.last_had_visual
                    and self.covariance_age + 1 < self.cfg.covariance_every_frames)
        self.last_had_visual = has_visual
        return self._estimate(t_ns, keep_cov)

    def _update(self, graph, values, t_ns: int) -> None:
        stamp = self._stamp(t_ns)
        stamps = {X(self.i): stamp, V(self.i): stamp, B(self.i): stamp}
        try:
            self.smoother.update(graph, values, stamps)
        except RuntimeError as e:
            raise BackendError(f"smoother update failed: {e}") from None
        self.index_of[t_ns] = self.i
        horizon = t_ns - int(self.cfg.lag_s * 1e9)
        for t in [t for t in self.index_of if t < horizon]:
            del self.index_of[t]

    def _estimate(self, t_ns: int, keep_cov: bool = False) -> BackendEstimate:
        """keep_cov: the last estimate's covariances stand for this one's (see BackendConfig)."""
        i = self.i
        try:
            est = self.smoother.calculateEstimate()
            pose = est.atPose3(X(i)).matrix()
            vel = np.array(est.atVector(V(i)))
            bias = from_gtsam_bias(est.atConstantBias(B(i)))
            if keep_cov and self.last is not None:
                last = self.last
                pc, vc, bc = last.pose_cov_tangent, last.velocity_cov_world, last.bias_cov
                self.covariance_age += 1
            elif self.cfg.compute_covariance:
                self.covariance_age = 0
                pc = np.array(self.smoother.marginalCovariance(X(i)))
                vc = np.array(self.smoother.marginalCovariance(V(i)))
                bc = np.array(self.smoother.marginalCovariance(B(i)))
            else:
                pc, vc, bc = np.eye(6) * np.nan, np.eye(3) * np.nan, np.eye(6) * np.nan
        except RuntimeError as e:
            raise BackendError(f"smoother estimate failed: {e}") from None
        if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(vel))):
            raise BackendError("smoother diverged (non-finite state)")
        self.last = BackendEstimate(t_ns, pose, vel, bias, pc, vc, bc)
        return self.last
