"""The flight controller's position estimate when GPS-denied (SIM_GPS_DENIED): vision + IMU.

What PX4's EKF2 does with EKF2_EV_CTRL (vision position + velocity) and no GPS, reduced to what
the stack needs to feel: a per-axis [position, velocity] Kalman filter in ENU.
- Predict at the physics rate with the FC's accelerometer: the true acceleration plus white noise
  of SIM_ACC_NOISE (the same noise its HIGHRES_IMU carries). No accelerometer bias is modelled,
  so dead-reckoning between vision samples drifts only by that noise.
- Correct with each vision ODOMETRY: position (variance from its covariance, floored at
  EKF2_EVP_NOISE^2) and velocity (floored at EKF2_EVV_NOISE^2); with EKF2_EV_NOISE_MD 1 the
  parameters alone, as PX4 (our VIO's covariance includes its accumulated drift: a slowly varying
  offset of the odom frame, not independent noise per sample, so it must not down-weight vision). Fusion is delayed like EKF2's:
  the innovation is taken against the estimate at the sample's stamp (a short history), and the
  correction applied to the current state, so VIO latency does not turn into lag.
- Frames: the VIO's odom frame starts wherever and however the VIO initialised. Like EKF2 without
  vision yaw fusion, the first sample (and the first after a reset or a gap longer than
  SIM_EV_REALIGN_T) aligns it: a yaw offset (the FC's heading minus the vision heading) and a
  translation that puts that sample on the current estimate, so the estimate stays continuous.
- Attitude is the FC's own (the airframe's; EKF2's attitude from gyro + accel + mag is not what
  this simulator studies). Ground contact is physical (the land detector's input).
- Valid while vision was fused within EKF2_NOAID_TOUT (PX4's dead-reckoning limit, default 5 s);
  before the first sample there is no position at all: arming and OFFBOARD are refused with PX4's
  "Navigation error: No valid position estimate" (commander.py).
When SIM_GPS_DENIED is false the estimate is the truth (the GPS-like position, as before).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable

import numpy as np

from aeroperception.services.mavlink.frames import quat_to_rotmat, wrap_pi, yaw_from_q
from aeroperception.services.runtime.params import ParamSet

from .dynamics import RigidBodyState

_HISTORY_S = 1.0          # how far back a delayed vision sample can be fused
_MAX_FUTURE_NS = 50_000_000


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class VisionEstimator:
    """Position/velocity of the vehicle as the FC believes it. `step` once per physics step;
    `on_vision` per received vision sample. `position_enu_m` / `velocity_enu_mps` are the
    estimate (the truth when not GPS-denied)."""

    def __init__(self, params: ParamSet, truth: RigidBodyState, rng: np.random.Generator):
        self.p = params
        self.truth = truth
        self.rng = rng
        # vision stamps - epoch = sim time: an int, a getter (the runner's epoch moves when it
        # re-anchors), or None: learnt (the smallest delay seen counts as zero)
        self.epoch_ns: int | Callable[[], int] | None = None
        self.counters = {"vision_fused": 0, "vision_rejected": 0, "vision_late": 0, "ev_alignments": 0}
        self.reset()

    def reset(self) -> None:
        self.position_enu_m = self.truth.position_enu_m.copy()
        self.velocity_enu_mps = self.truth.velocity_enu_mps.copy()
        self.P = np.tile(np.diag([0.01, 0.01]), (3, 1, 1))  # per axis [p, v]
        self.last_fused_ns: int | None = None
        self.aligned = False
        self.R_enu_odom = np.eye(3)
        self.t_enu_odom = np.zeros(3)
        self.reset_counter: int | None = None
        self.history: deque[tuple[int, np.ndarray, np.ndarray]] = deque()
        self._learnt_offset_ns: int | None = None
        self._was_denied = False

    # ------------------------------------------------------------------ state

    @property
    def gps_denied(self) -> bool:
        return bool(self.p.SIM_GPS_DENIED)

    def valid(self, now_ns: int) -> bool:
        """The FC has a local position (PX4: local_position xy_valid)."""
        if not self.gps_denied:
            return bool(self.p.SIM_POS_VALID)
        return (self.p.SIM_POS_VALID and self.last_fused_ns is not None
                and now_ns - self.last_fused_ns <= self.p.EKF2_NOAID_TOUT * 1e9)

    def position_sigma_m(self) -> float:
        return float(math.sqrt(max(self.P[0, 0, 0], self.P[1, 0, 0])))

    # ------------------------------------------------------------------ predict

    def step(self, dt_s: float, now_ns: int) -> None:
        if not self.gps_denied:
            if self._was_denied:
                self.reset()
            return
        if not self._was_denied:   # switched on (boot or live): start from where we are, unaligned
            self.reset()
            self._was_denied = True
            self.position_enu_m = self.position_enu_m.copy()
            self.velocity_enu_mps = self.velocity_enu_mps.copy()
        s = self.truth
        if s.resting:
            # On the ground the FC knows it is still (PX4's zero-velocity update when landed).
            self.velocity_enu_mps = np.zeros(3)
        else:
            sigma = self.p.SIM_ACC_NOISE
            acc = s.accel_enu_mps2 + self.rng.standard_normal(3) * sigma
            self.position_enu_m = self.position_enu_m + self.velocity_enu_mps * dt_s + 0.5 * acc * dt_s * dt_s
            self.velocity_enu_mps = self.velocity_enu_mps + acc * dt_s
            F = np.array([[1.0, dt_s], [0.0, 1.0]])
            G = np.array([0.5 * dt_s * dt_s, dt_s])
            Q = np.outer(G, G) * max(sigma, 1e-3) ** 2
            self.P = F @ self.P @ F.T + Q
        self.history.append((now_ns, self.position_enu_m.copy(), self.velocity_enu_mps.copy()))
        while self.history and now_ns - self.history[0][0] > _HISTORY_S * 1e9:
            self.history.popleft()

    # ------------------------------------------------------------------ correct

    def _sim_ns(self, stamp_ns: int, now_ns: int) -> int:
        if self.epoch_ns is not None:
            return stamp_ns - (self.epoch_ns() if callable(self.epoch_ns) else self.epoch_ns)
        off = stamp_ns - now_ns
        if self._learnt_offset_ns is None or off > self._learnt_offset_ns:
            self._learnt_offset_ns = off     # the smallest delay seen counts as zero
        return stamp_ns - self._learnt_offset_ns

    def _at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The estimate at sim time t (newest not after it)."""
        best = None
        for item in reversed(self.history):
            if item[0] <= t_ns:
                best = item
                break
        if best is None:
            return self.position_enu_m, self.velocity_enu_mps
        return best[1], best[2]

    def on_vision(self, now_ns: int, stamp_ns: int, position_odom_m, q_odom_body, velocity_body_mps=None,
                  position_var_m2=None, velocity_var_m2=None, reset_counter: int | None = None) -> bool:
        """Fuse one vision sample (odom frame, FLU body). Returns whether it was fused."""
        if not self.gps_denied:
            return False
        p_odom = np.asarray(position_odom_m, float)
        q = np.asarray(q_odom_body, float)
        if not (np.all(np.isfinite(p_odom)) and np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 0.1):
            self.counters["vision_rejected"] += 1
            return False
        t_ns = self._sim_ns(stamp_ns, now_ns)
        if t_ns > now_ns + _MAX_FUTURE_NS or now_ns - t_ns > _HISTORY_S * 1e9:
            self.counters["vision_late"] += 1
            return False
        gap = self.last_fused_ns is None or now_ns - self.last_fused_ns > self.p.SIM_EV_REALIGN_T * 1e9
        reset = reset_counter is not None and self.reset_counter is not None and reset_counter != self.reset_counter
        self.reset_counter = reset_counter
        p_then, _ = self._at(t_ns)
        if not self.aligned or gap or reset:
            yaw = wrap_pi(self.truth.yaw_rad - yaw_from_q(q))
            self.R_enu_odom = _rot_z(yaw)
            self.t_enu_odom = p_then - self.R_enu_odom @ p_odom
            self.aligned = True
            self.counters["ev_alignments"] += 1
        z_pos = self.R_enu_odom @ p_odom + self.t_enu_odom
        r_pos = np.full(3, self.p.EKF2_EVP_NOISE ** 2)
        use_reported = not self.p.EKF2_EV_NOISE_MD
        if use_reported and position_var_m2 is not None:
            var = np.asarray(position_var_m2, float)
            r_pos = np.where(np.isfinite(var), np.maximum(var, r_pos), r_pos)
        self._update(0, z_pos - p_then, r_pos)
        if velocity_body_mps is not None and np.all(np.isfinite(velocity_body_mps)):
            R_odom_body = quat_to_rotmat(q)
            z_vel = self.R_enu_odom @ R_odom_body @ np.asarray(velocity_body_mps, float)
            _, v_then = self._at(t_ns)
            r_vel = np.full(3, self.p.EKF2_EVV_NOISE ** 2)
            if use_reported and velocity_var_m2 is not None:
                var = np.asarray(velocity_var_m2, float)
                r_vel = np.where(np.isfinite(var), np.maximum(var, r_vel), r_vel)
            self._update(1, z_vel - v_then, r_vel)
        self.last_fused_ns = now_ns
        self.counters["vision_fused"] += 1
        return True

    def _update(self, idx: int, innovation: np.ndarray, r: np.ndarray) -> None:
        """Scalar Kalman update per axis of state element idx (0 position, 1 velocity); the
        correction shifts the current state and the history alike."""
        dx = np.zeros((3, 2))
        for ax in range(3):
            P = self.P[ax]
            s = P[idx, idx] + r[ax]
            k = P[:, idx] / s
            dx[ax] = k * innovation[ax]
            self.P[ax] = P - np.outer(k, P[idx, :])
        self.position_enu_m = self.position_enu_m + dx[:, 0]
        self.velocity_enu_mps = self.velocity_enu_mps + dx[:, 1]
        self.history = deque((t, p + dx[:, 0], v + dx[:, 1]) for t, p, v in self.history)


class EstimatedState:
    """What the commander and the position controller read: the estimator's position and
    velocity over the airframe's attitude, acceleration (IMU) and ground contact."""

    def __init__(self, truth: RigidBodyState, estimator: VisionEstimator):
        self._truth = truth
        self._est = estimator

    @property
    def position_enu_m(self) -> np.ndarray:
        return self._est.position_enu_m if self._est.gps_denied else self._truth.position_enu_m

    @property
    def velocity_enu_mps(self) -> np.ndarray:
        return self._est.velocity_enu_mps if self._est.gps_denied else self._truth.velocity_enu_mps

    # Read every physics step (land detector, position control): plain properties, as __getattr__
    # costs ~0.5 us a read.
    @property
    def resting(self) -> bool:
        return self._truth.resting

    @property
    def on_ground(self) -> bool:
        return self._truth.on_ground

    @property
    def accel_enu_mps2(self) -> np.ndarray:
        return self._truth.accel_enu_mps2

    @property
    def yaw_rad(self) -> float:
        return self._truth.yaw_rad

    def __getattr__(self, name):   # attitude, rates, thrust, ground height, ...
        return getattr(self._truth, name)
