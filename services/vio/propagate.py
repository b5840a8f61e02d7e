"""IMU-rate odometry between frames: the newest smoother estimate carried forward with the IMU.

Why: a flight controller's estimator fuses vision only when poses come often and soon enough
(PX4's EKF2 starts and keeps vision fusion only with samples < 0.2 s apart, and fuses a sample only
while its stamp is inside its delay horizon, EKF2_DELAY_MAX 0.2 s + 0.1 s). Frames can come slower
and later than that: cameras rendered on a loaded machine gave 1-4 Hz, 0.4-0.8 s late, and EKF2
stopped fusing and fell back to dead reckoning. So between frames the pose is predicted to each IMU
sample's time from the last estimate (pose, velocity, bias) with the same preintegration the
smoother uses, and stamped at that sample: a pose for the time it holds, as soon as the IMU sample
is in. A new frame's estimate (stamped at its exposure, in the past) replaces the base and is
carried forward over the samples that came since.

Beyond `max_horizon_s` after the newest estimate nothing is predicted: IMU-only position error
grows with t^2, and the consumer's own timeout (EKF2: vision stopped) must take over. An IMU clock
going back by more than `restart_s` (a replay or simulator restart) starts over.
"""
from __future__ import annotations

import bisect
import dataclasses
import threading

import numpy as np

from .dto import ImuSample, VioOutput
from .imu import ImuNoise, ImuPreintegrator, to_gtsam_bias


class ImuPropagator:
    """`on_estimate(out)` with each frame's output, `on_imu(sample)` with each IMU sample: returns a
    VioOutput at the sample's time when one is due (`rate_hz`), else None. Thread-safe (the frame
    worker and the IMU callback call it concurrently). `reset()` when the estimator restarts."""

    def __init__(self, noise: ImuNoise, rate_hz: float, max_horizon_s: float = 2.0, restart_s: float = 1.0):
        self.preint = ImuPreintegrator(noise)
        self.period_ns = int(1e9 / rate_hz)
        self.max_horizon_ns = int(max_horizon_s * 1e9)
        self.restart_ns = int(restart_s * 1e9)
        self.lock = threading.Lock()
        self.imu: list[ImuSample] = []     # sorted, trimmed to the horizon behind the newest sample
        self.base: VioOutput | None = None
        self.pim = None                    # preintegrated from base.stamp_ns to `self.pim_t_ns`
        self.pim_t_ns = 0
        self.last_out_ns = 0
        self.counters = {"propagated": 0, "imu_out_of_order": 0, "beyond_horizon": 0, "imu_restarts": 0}

    def reset(self) -> None:
        with self.lock:
            self.base = self.pim = None

    def on_estimate(self, out: VioOutput) -> None:
        with self.lock:
            if self.base is not None and out.stamp_ns <= self.base.stamp_ns:
                return
            self.base = out
            samples = self.imu[max(0, bisect.bisect_right(self.imu, out.stamp_ns, key=lambda s: s.t_ns) - 1):]
            end = samples[-1].t_ns if samples else out.stamp_ns
            if end <= out.stamp_ns:
                self.pim, self.pim_t_ns = self.preint.integrate([], out.stamp_ns, out.stamp_ns, out.imu_bias), out.stamp_ns
            else:
                self.pim, self.pim_t_ns = self.preint.integrate(samples, out.stamp_ns, end, out.imu_bias), end

    def on_imu(self, sample: ImuSample) -> VioOutput | None:
        with self.lock:
            if self.imu and sample.t_ns < self.imu[-1].t_ns - self.restart_ns:
                self.counters["imu_restarts"] += 1
                self.imu, self.base, self.pim, self.last_out_ns = [], None, None, 0
            if self.imu and sample.t_ns <= self.imu[-1].t_ns:
                self.counters["imu_out_of_order"] += 1
                return None
            prev = self.imu[-1] if self.imu else None
            self.imu.append(sample)
            if self.imu[0].t_ns < sample.t_ns - 2 * self.max_horizon_ns:
                del self.imu[:bisect.bisect_left(self.imu, sample.t_ns - self.max_horizon_ns, key=lambda s: s.t_ns)]
            base = self.base
            if base is None or sample.t_ns <= self.pim_t_ns:
                return None
            if prev is not None:    # the previous sample holds until this one (zero-order hold)
                self.pim.integrateMeasurement(prev.accel_mps2, prev.gyro_radps, (sample.t_ns - self.pim_t_ns) * 1e-9)
                self.pim_t_ns = sample.t_ns
            if sample.t_ns - base.stamp_ns > self.max_horizon_ns:
                self.counters["beyond_horizon"] += 1
                return None
            if sample.t_ns - self.last_out_ns < self.period_ns or self.pim_t_ns != sample.t_ns:
                return None
            self.last_out_ns = sample.t_ns
            self.counters["propagated"] += 1
            return self._predict(base, sample)

    def _predict(self, base: VioOutput, sample: ImuSample) -> VioOutput:
        T, v = self.preint.predict(self.pim, base.world_T_body, base.velocity_world_mps, to_gtsam_bias(base.imu_bias))
        dt = (sample.t_ns - base.stamp_ns) * 1e-9
        R0, R = base.world_T_body[:3, :3], T[:3, :3]
        C = self.pim.preintMeasCov()                     # rotation, position, velocity (body at base), biases
        vel_cov_world = R0 @ base.twist_covariance_6x6[:3, :3] @ R0.T
        pose_cov = base.pose_covariance_6x6.copy()
        pose_cov[:3, :3] += dt * dt * vel_cov_world + R0 @ C[3:6, 3:6] @ R0.T
        pose_cov[3:, 3:] += R0 @ C[0:3, 0:3] @ R0.T
        twist_cov = base.twist_covariance_6x6.copy()
        twist_cov[:3, :3] = R.T @ (vel_cov_world + R0 @ C[6:9, 6:9] @ R0.T) @ R
        return dataclasses.replace(
            base, stamp_ns=sample.t_ns, world_T_body=T, velocity_world_mps=v,
            angular_velocity_body_radps=np.asarray(sample.gyro_radps, float) - base.imu_bias.gyro_radps,
            pose_covariance_6x6=pose_cov, twist_covariance_6x6=twist_cov, keyframe=False, timings_ms={},
            relative_pose_T=base.relative_pose_T @ np.linalg.inv(base.world_T_body) @ T)
