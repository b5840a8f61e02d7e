"""The strategy seam (requirement VIO-5): `VioStrategy` (process_frame / reset_to_warm_start /
health_snapshot), the registry the `strategy` parameter selects from at start, and the KLT
strategies built on frontend.py + backend.py.

`klt_stereo` (default): stereo PnP relative poses + IMU in the fixed-lag smoother; metric.
`klt_mono`: the left camera only; the visual factor constrains rotation, scale comes from the IMU
alone (drifts in position; a baseline and a fallback, not for GPS-denied flight).
`okvis2` / `vins_mono` are named by the VIO specification but not built here: asking for them
raises StrategyNotAvailableError listing what exists.
"""
from __future__ import annotations

import bisect
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from aeroperception.services.runtime.rotations import quat_from_axis_angle, quat_to_rotmat

from . import health as H
from .backend import Backend, BackendConfig, BackendError, adjoint, tangent_to_world_cov
from .calibration import CameraCalibration
from .drift import DriftConfig, DriftCovariance
from .dto import (
    DEGRADED, LOST, FeatureQuality, ImuBias, ImuSample, ImuWindow, NavCameraFrame,
    StrategyNotAvailableError, VioDegradedError, VioFatalError, StrategyHealth, VioInitializingError,
    VioOutput, WarmStartPose,
)
from .frontend import FrontEnd, FrontEndConfig
from .imu import ImuNoise, gravity_aligned_rotation


@dataclass
class VioConfig:
    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    imu: ImuNoise = field(default_factory=ImuNoise)
    drift: DriftConfig = field(default_factory=DriftConfig)
    init_imu_s: float = 0.2            # IMU averaged for gravity alignment
    # Still (mean gyro = gyro bias, velocity zero) only if all three hold over init_imu_s; MH_01's
    # hand-carried start passes the first alone (accel std 0.43) while turning at 0.46 rad/s
    # with |a| 0.75 m/s^2 below g: taken as still, that turn became a 0.45 rad/s "bias".
    still_accel_std_mps2: float = 0.5  # accel standard deviation below this
    still_accel_norm_tol_mps2: float = 0.3   # | |mean accel| - g | below this
    still_gyro_max_radps: float = 0.2  # |mean gyro| below this (a larger gyro bias is a fault)
    moving_init_velocity_sigma_mps: float = 3.0   # velocity prior when starting in motion
    lost_after_frames: int = 10
    imu_gap_warn_s: float = 0.05
    imu_gap_reset_s: float = 1.0
    time_jump_reset_s: float = 1.0
    # A restart that continues the odom frame carries the last estimate over the time it missed at
    # its velocity and turn rate, up to this long (beyond it the vehicle's motion is anybody's guess:
    # the last pose stands)
    continue_carry_max_s: float = 2.0
    imu_buffer_s: float = 5.0


class VioStrategy(ABC):
    name: ClassVar[str] = ""

    @abstractmethod
    def process_frame(self, frame: NavCameraFrame, imu: ImuWindow,
                      calibration: CameraCalibration | None) -> VioOutput:
        """One frame. Raises VioInitializingError (no output yet), VioDegradedError (output in
        `.output`, may be None for a dropped frame) or VioFatalError (LOST / needs a reset)."""

    @abstractmethod
    def reset_to_warm_start(self, warm: WarmStartPose) -> None:
        """Restart from a known pose (e.g. after a companion reboot); INIT until the next frame."""

    @abstractmethod
    def health_snapshot(self) -> StrategyHealth:
        ...


class KltVio(VioStrategy):
    stereo: ClassVar[bool] = True

    def __init__(self, config: VioConfig | None = None):
        self.cfg = config or VioConfig()
        self.backend = Backend(self.cfg.imu, self.cfg.backend)
        self.drift = DriftCovariance(self.cfg.drift)   # odom-frame drift outside the window
        self.calib: CameraCalibration | None = None
        self.frontend: FrontEnd | None = None
        self.imu: list[ImuSample] = []   # sorted by time, trimmed to imu_buffer_s
        self.health = StrategyHealth()
        self.warm: WarmStartPose | None = None
        self.last_t_ns: int | None = None
        self.kf_world_T_body = np.eye(4)
        self.last_gyro = np.zeros(3)
        self.continuing = False   # the next initialisation continues the current odom frame
        self.continue_from: tuple[int, np.ndarray] | None = None   # (stamp, body rate) of the pose it continues
        self.initialisations = 0  # successful starts; each after the first is a reset of the odom pose
        self.counters = {"frames": 0, "outputs": 0, "bad_frames": 0, "time_backwards": 0,
                         "imu_gaps": 0, "imu_dropped": 0, "resets": 0, "visual_fixes": 0}
        self.last_timings: dict[str, float] = {}

    # ------------------------------------------------------------ seam

    def health_snapshot(self) -> StrategyHealth:
        h = self.health
        return StrategyHealth(h.state, h.consecutive_lost, h.bias_norm, h.message)

    def reset_to_warm_start(self, warm: WarmStartPose) -> None:
        T = np.asarray(warm.world_T_body, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise VioFatalError("warm start pose must be a finite 4x4 matrix")
        self._reset("warm start requested")
        self.warm = warm

    @property
    def keyframes(self) -> int:
        return self.frontend.keyframes if self.frontend else 0

    # ------------------------------------------------------------ internals

    def _reset(self, why: str, keep_pose: bool = False) -> None:
        """keep_pose: re-initialise from the last estimate (pose incl. yaw, bias; velocity re-found
        from stereo + IMU), so the odom frame stays continuous through a restart of the smoother
        instead of jumping back to the origin with yaw 0 (and its drift term is kept)."""
        last = self.backend.last
        self.continuing = keep_pose and last is not None
        if self.continuing:
            self.warm = WarmStartPose(last.world_T_body, last.velocity_world_mps, last.bias)
            self.continue_from = (last.t_ns, self.last_gyro - last.bias.gyro_radps)
        self.backend.reset()
        if self.frontend:
            self.frontend.reset()
        self.counters["resets"] += 1
        self.health = StrategyHealth(H.next_state(self.health.state, H.RESET), 0, self.health.bias_norm, why)
        self.last_t_ns = None

    def _set_calibration(self, calib: CameraCalibration) -> None:
        if calib is self.calib:
            return
        if self.stereo and not calib.is_stereo:
            raise VioInitializingError("klt_stereo needs a stereo calibration (sensors/camera/right/info)")
        self.calib = calib
        self.frontend = FrontEnd(calib, self.cfg.frontend, stereo=self.stereo)

    def _add_imu(self, window: ImuWindow) -> None:
        last = self.imu[-1].t_ns if self.imu else None
        for s in sorted(window.samples, key=lambda s: s.t_ns):
            g, a = np.asarray(s.gyro_radps, float), np.asarray(s.accel_mps2, float)
            if g.shape != (3,) or a.shape != (3,) or not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
                self.counters["imu_dropped"] += 1
                continue
            if last is not None and s.t_ns <= last:
                self.counters["imu_dropped"] += 1   # duplicate or time going backwards
                continue
            self.imu.append(ImuSample(int(s.t_ns), g, a))
            last = s.t_ns
        horizon = (last or 0) - int(self.cfg.imu_buffer_s * 1e9)
        if self.imu and self.imu[0].t_ns < horizon - int(1e9):   # trim in chunks: O(1) amortised
            del self.imu[:bisect.bisect_left(self.imu, horizon, key=lambda s: s.t_ns)]
        if self.imu:
            self.last_gyro = self.imu[-1].gyro_radps

    def _imu_between(self, t0_ns: int, t1_ns: int) -> tuple[list[ImuSample], float]:
        """Samples covering [t0, t1] (the last one at or before t0 included) and the longest gap (s)."""
        buf = self.imu
        lo = bisect.bisect_right(buf, t0_ns, key=lambda s: s.t_ns)
        hi = bisect.bisect_right(buf, t1_ns, key=lambda s: s.t_ns)
        out = [buf[k] for k in range(max(lo - 1, 0), hi)]
        ts = [t0_ns] + [s.t_ns for s in out if s.t_ns > t0_ns] + [t1_ns]
        gap = max(b - a for a, b in zip(ts, ts[1:])) * 1e-9
        return out, gap

    def _initialize(self, frame: NavCameraFrame, problem: str | None) -> VioOutput:
        t = frame.capture_timestamp_ns
        if problem:
            raise VioInitializingError(problem)
        if self.warm is None:
            lo = bisect.bisect_left(self.imu, t - int(self.cfg.init_imu_s * 1e9), key=lambda s: s.t_ns)
            win = self.imu[lo:bisect.bisect_right(self.imu, t + int(0.01e9), key=lambda s: s.t_ns)]
            span = (win[-1].t_ns - win[0].t_ns) * 1e-9 if len(win) > 1 else 0.0
            if span < 0.8 * self.cfg.init_imu_s:
                raise VioInitializingError(f"waiting for IMU ({span:.2f} of {self.cfg.init_imu_s:.2f} s)")
        self.frontend.reset()
        res = self.frontend.process(t, frame.left, frame.right)
        if len(self.frontend.kf_px) < self.cfg.frontend.good_inliers:
            raise VioInitializingError(f"too few features to start ({len(self.frontend.kf_px)} of "
                                       f"{self.cfg.frontend.good_inliers})")
        vel_sigma, moving = None, False
        if self.warm is not None:
            w, self.warm = self.warm, None
            T, vel, bias = np.asarray(w.world_T_body, float), np.asarray(w.velocity_world_mps, float), w.bias
            if self.continuing:
                T = self._carried_over(T, vel, t)
                vel_sigma = self.cfg.moving_init_velocity_sigma_mps   # the last velocity is stale
        else:
            acc = np.array([s.accel_mps2 for s in win])
            gyr = np.array([s.gyro_radps for s in win])
            T = np.eye(4)
            T[:3, :3] = gravity_aligned_rotation(acc.mean(axis=0))
            still = self._still(acc, gyr)
            moving = not still
            bias = ImuBias(np.zeros(3), gyr.mean(axis=0) if still else np.zeros(3))
            vel = np.zeros(3)
            # Started in flight (a restart): velocity unknown; stereo + IMU find it within frames.
            vel_sigma = None if still else self.cfg.moving_init_velocity_sigma_mps
        try:
            est = self.backend.initialize(t, T, vel, bias, vel_sigma, moving)
        except BackendError as e:
            raise VioInitializingError(str(e)) from None
        self.kf_world_T_body = est.world_T_body
        if not self.continuing:
            self.drift.reset()
        self.continuing = False
        self.health = StrategyHealth(H.next_state(self.health.state, H.INITIALIZED), 0, est.bias.norm,
                                f"initialised ({len(self.frontend.kf_px)} stereo features)")
        self.last_t_ns = t
        self.initialisations += 1
        return self._output(frame, est, res.quality, True, res.timings_ms, inliers=len(self.frontend.kf_px))

    def _still(self, acc: np.ndarray, gyr: np.ndarray) -> bool:
        """Is the vehicle at rest over these IMU samples (N, 3)? See VioConfig."""
        c = self.cfg
        return (float(np.max(acc.std(axis=0))) < c.still_accel_std_mps2
                and abs(float(np.linalg.norm(acc.mean(axis=0))) - self.cfg.imu.gravity_mps2) < c.still_accel_norm_tol_mps2
                and float(np.linalg.norm(gyr.mean(axis=0))) < c.still_gyro_max_radps)

    def _carried_over(self, T: np.ndarray, vel: np.ndarray, t_ns: int) -> np.ndarray:
        """The pose a continuing restart starts from: the last estimate moved on to `t_ns` at its
        velocity and the body rate its IMU gives now. Without it a vehicle in motion jumped back by all it flew in the gap
        (1.3 s without IMU at 2.5 m/s: 3.3 m, and its yaw rate's worth of heading for good)."""
        t0, rate = self.continue_from or (t_ns, np.zeros(3))
        dt = (t_ns - t0) * 1e-9
        if not 0.0 < dt <= self.cfg.continue_carry_max_s:
            return T
        out = T.copy()
        out[:3, 3] += vel * dt
        out[:3, :3] = T[:3, :3] @ quat_to_rotmat(quat_from_axis_angle(rate * dt))
        return out

    def _output(self, frame, est, quality: FeatureQuality, keyframe: bool, timings, inliers: int | None) -> VioOutput:
        """`inliers`: the visual fix's (stereo features at initialisation; None: no fix, IMU only)."""
        R = est.world_T_body[:3, :3]
        vel_body_cov = R.T @ est.velocity_cov_world @ R
        twist_cov = np.zeros((6, 6))
        twist_cov[:3, :3] = vel_body_cov
        gyro_var = self.cfg.imu.gyro_noise_density ** 2 * 200.0
        twist_cov[3:, 3:] = est.bias_cov[3:, 3:] + gyro_var * np.eye(3)
        self.counters["outputs"] += 1
        self.drift.update(est.world_T_body)
        # window marginal + the drift accumulated outside the window: honest over a long flight
        pose_cov = tangent_to_world_cov(est.world_T_body, est.pose_cov_tangent) + self.drift.covariance()
        return VioOutput(
            frame_id=frame.frame_id, stamp_ns=frame.capture_timestamp_ns,
            relative_pose_T=np.linalg.inv(self.kf_world_T_body) @ est.world_T_body,
            pose_covariance_6x6=pose_cov,
            imu_bias=est.bias, feature_quality=quality, world_T_body=est.world_T_body,
            velocity_world_mps=est.velocity_world_mps,
            angular_velocity_body_radps=self.last_gyro - est.bias.gyro_radps,
            twist_covariance_6x6=twist_cov, keyframe=keyframe, timings_ms=dict(timings),
            emitted_at_ns=time.monotonic_ns(), reset_counter=max(0, self.initialisations - 1),
            quality_pct=H.quality_pct(self.health.state, inliers, self.cfg.frontend.good_inliers,
                                      self.cfg.frontend.keyframe_min_inliers))

    # ------------------------------------------------------------ per frame

    def process_frame(self, frame: NavCameraFrame, imu: ImuWindow,
                      calibration: CameraCalibration | None) -> VioOutput:
        t_start = time.perf_counter()
        self.counters["frames"] += 1
        self._add_imu(imu)
        if calibration is None:
            self.health.message = "no camera calibration yet (sensors/camera/*/info)"
            raise VioInitializingError(self.health.message)
        self._set_calibration(calibration)
        t = int(frame.capture_timestamp_ns)
        if self.last_t_ns is not None and t <= self.last_t_ns:
            back_s = (self.last_t_ns - t) * 1e-9
            self.counters["time_backwards"] += 1
            if back_s > self.cfg.time_jump_reset_s:
                self._reset(f"time jumped back {back_s:.1f} s (replay or sim restart): re-initialising")
                self.imu.clear()
                raise VioInitializingError(self.health.message)
            raise VioDegradedError(f"frame time went backwards by {back_s * 1e3:.0f} ms: frame dropped")
        problem = self.calib.check_image(frame.left, "left")
        if not problem and self.stereo:
            problem = self.calib.check_image(frame.right, "right")
        if problem:
            self.counters["bad_frames"] += 1
        if not self.backend.initialized:
            self.health.message = problem or self.health.message
            try:
                out = self._initialize(frame, problem)
            except VioInitializingError as e:
                self.health.message = str(e)
                raise
            out.timings_ms["total"] = (time.perf_counter() - t_start) * 1e3
            return out

        samples, gap_s = self._imu_between(self.last_t_ns, t)
        if gap_s > self.cfg.imu_gap_reset_s or not samples:
            self.counters["imu_gaps"] += 1
            self._reset(f"IMU gap of {gap_s:.2f} s: re-initialising", keep_pose=True)
            raise VioInitializingError(self.health.message)
        notes = []
        if gap_s > self.cfg.imu_gap_warn_s:
            self.counters["imu_gaps"] += 1
            notes.append(f"IMU gap {gap_s * 1e3:.0f} ms")
        t_fe = time.perf_counter()
        if problem:
            notes.append(problem)
            self.frontend.reset()
            res = None
        else:
            res = self.frontend.process(t, frame.left, frame.right)
        timings = dict(res.timings_ms) if res else {}
        timings["frontend"] = (time.perf_counter() - t_fe) * 1e3
        visual = None
        if res is not None and res.T_kf_cur is not None:
            T_br = self.calib.T_body_rect
            T_rel = T_br @ res.T_kf_cur @ np.linalg.inv(T_br)
            Ad = adjoint(T_br)
            visual = (res.keyframe_t_ns, T_rel, Ad @ res.cov6 @ Ad.T)
            self.counters["visual_fixes"] += 1
        t_be = time.perf_counter()
        try:
            est = self.backend.add_frame(t, samples, visual)
        except BackendError as e:
            self._reset(f"{e}: re-initialising", keep_pose=True)
            raise VioFatalError(self.health.message) from None
        timings["backend"] = (time.perf_counter() - t_be) * 1e3
        self.last_t_ns = t
        if res is not None and res.new_keyframe:
            self.kf_world_T_body = est.world_T_body

        h = self.health
        if visual is not None:
            h.consecutive_lost = 0
            event = H.GOOD if (res.status == "ok" and not notes) else H.WEAK
            if res.status == "weak":
                notes.append(f"few inliers ({res.quality.inliers})")
        else:
            h.consecutive_lost += 1
            if res is not None:
                notes.append(res.message)
            event = H.MISS_LIMIT if h.consecutive_lost >= self.cfg.lost_after_frames else H.MISS
        h.state = H.next_state(h.state, event)
        h.bias_norm = est.bias.norm
        h.message = "; ".join(notes) if notes else "tracking"
        quality = res.quality if res is not None else FeatureQuality()
        out = self._output(frame, est, quality, bool(res and res.new_keyframe), timings,
                           inliers=quality.inliers if visual is not None else None)
        out.timings_ms["total"] = (time.perf_counter() - t_start) * 1e3
        self.last_timings = out.timings_ms
        if h.state == LOST:
            raise VioFatalError(f"LOST: no visual fix for {h.consecutive_lost} frames ({h.message})")
        if h.state == DEGRADED:
            raise VioDegradedError(h.message, out)
        return out


class KltStereo(KltVio):
    name = "klt_stereo"
    stereo = True


class KltMono(KltVio):
    name = "klt_mono"
    stereo = False


STRATEGIES: dict[str, type[VioStrategy]] = {KltStereo.name: KltStereo, KltMono.name: KltMono}
NOT_BUILT = {
    "okvis2": "OKVIS2 (C++) is not built into this installation",
    "vins_mono": "VINS-Mono (C++) is not built into this installation",
}


def create_strategy(name: str, config: VioConfig | None = None) -> VioStrategy:
    """The registry: a strategy by name, or StrategyNotAvailableError naming what exists."""
    cls = STRATEGIES.get(name)
    if cls is None:
        why = NOT_BUILT.get(name, "unknown strategy")
        raise StrategyNotAvailableError(f"VIO strategy {name!r}: {why}; available: {', '.join(STRATEGIES)}")
    return cls(config)
