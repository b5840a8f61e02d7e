"""Follow mode: the simulator renders the scenario's sensors for an external flight controller.

With PX4 SITL (SIH: physics inside PX4) the vehicle is PX4's, not ours: the simulator has no
physics and no MAVLink of its own. It follows the FC's ground truth, which fmu republishes from
MAVLink as fmu/out/vehicle_ground_truth (ENU about the FC's local origin, stamped on the clock of
the FC's IMU that fmu publishes as sensors/imu), and renders camera, LiDAR, sim/truth/** and
truth boxes from that pose and that stamp. The scenario's objects keep their coordinates in the
FC's local frame (its origin is where EKF2 started: the pad, within its GPS error); only the
height is shifted so that the vehicle standing on its pad stands on the scenario's ground.

Plain logic here (no Zenoh): `Follower` turns each ground-truth message into the VehicleTruth the
renderers take; `ImuLag` measures how far those stamps are from the FC IMU's clock.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np

from aeroperception.schemas import LandedState, VehicleState

from .truth import VehicleTruth


class Follower:
    """Ground-truth messages -> VehicleTruth in the scenario's frame.

    The FC's local origin is not on the ground (EKF2 takes its height origin from GPS/baro: the
    SIH vehicle on its pad was 0.34 m above it): the first sample of the vehicle disarmed on the
    ground fixes the height shift that puts it on the scenario's ground, kept from then on (a
    follower started in the air renders unshifted until the vehicle lands, and says so).
    The FC's height on the ground is not the same at every landing (PX4 SIH: 0.12 m on its pad,
    0.06 m after a 5 m hop), so a pose below the scenario's ground is raised onto it (counted in
    `below_ground`, the deepest in `below_ground_max_m`): the cameras sit 3 cm above the body
    origin, and a vehicle rendered 6 cm under the ground sees only the sky colour (VIO lost).

    A gap of more than `outage_s` between samples is an outage (the FC or fmu restarted): counted,
    with the newest one's length and stamp, so a gap shorter than a diagnostics period is still
    reported after the truth came back."""

    def __init__(self, ground_height_m: Callable[[float, float], float], outage_s: float = 1.0):
        self.ground_height_m = ground_height_m
        self.outage_ns = int(outage_s * 1e9)
        self.z_shift_m: float | None = None
        self.samples = self.rejected = self.out_of_order = self.outages = self.below_ground = 0
        self.below_ground_max_m = 0.0
        self.last_outage: tuple[float, int] | None = None     # (length s, stamp it ended)
        self.last_stamp_ns = 0
        self._prev: tuple[int, np.ndarray] | None = None     # (stamp, velocity) for the acceleration

    def truth(self, m: VehicleState) -> VehicleTruth | None:
        """The truth to render at, or None: for a sample that cannot be one (non-finite: counted in
        `rejected`), or one not newer than the last (a duplicate, or stamped out of order by a
        burst of link delay: ~0.6 % of PX4's, counted in `out_of_order`)."""
        p, v = m.position_m.to_array(), m.velocity_mps.to_array()
        q, w = m.orientation.to_array(), m.angular_velocity_radps.to_array()
        stamp = m.header.stamp_ns
        if not all(np.all(np.isfinite(a)) for a in (p, v, q, w)) or np.linalg.norm(q) < 0.5:
            self.rejected += 1
            return None
        if stamp <= self.last_stamp_ns:
            self.out_of_order += 1
            return None
        if self.z_shift_m is None and not m.armed and m.landed_state == LandedState.ON_GROUND:
            self.z_shift_m = self.ground_height_m(p[0], p[1]) - p[2]
        p = p + np.array([0.0, 0.0, self.z_shift_m or 0.0])
        depth_m = self.ground_height_m(p[0], p[1]) - p[2]
        if depth_m > 0.0:
            p[2] += depth_m
            self.below_ground += 1
            self.below_ground_max_m = max(self.below_ground_max_m, depth_m)
        accel = np.zeros(3)
        if self._prev is not None and 0 < stamp - self._prev[0] < 0.2e9:
            accel = (v - self._prev[1]) / ((stamp - self._prev[0]) * 1e-9)
        self._prev = (stamp, v)
        if self.last_stamp_ns and stamp - self.last_stamp_ns > self.outage_ns:
            self.outages += 1
            self.last_outage = ((stamp - self.last_stamp_ns) / 1e9, stamp)
        self.last_stamp_ns = stamp
        self.samples += 1
        return VehicleTruth(stamp_ns=stamp, position_enu_m=p, velocity_enu_mps=v, accel_enu_mps2=accel,
                            q_enu_flu=q / np.linalg.norm(q), angular_velocity_flu_radps=w)


class ImuLag:
    """How far the truth's stamps (the images' stamps) are from the FC IMU's clock, measured: the
    lag that best lines up the truth's body rates with the IMU's gyro (both FLU). Needs rotation
    to see (`min_rate_radps` RMS over the window), otherwise None; a positive lag means the
    truth is stamped late against the IMU. Resolution ~1 ms (linear interpolation of 100 Hz rates).
    The median of the last `keep` measurements is reported: a window of little rotation has a flat
    optimum (PX4 SIH hovering: -4 ms in 12 of 14 windows of 4 s, -15 ms in the two calmest)."""

    def __init__(self, window_s: float = 4.0, max_lag_s: float = 0.04, step_s: float = 0.001,
                 min_rate_radps: float = 0.05, keep: int = 15):
        self.window_ns = int(window_s * 1e9)
        self.lags_ns = np.arange(-max_lag_s, max_lag_s + step_s / 2, step_s) * 1e9
        self.min_rate = min_rate_radps
        self.imu: deque[tuple[int, np.ndarray]] = deque()
        self.truth: deque[tuple[int, np.ndarray]] = deque()
        self.measured: deque[float] = deque(maxlen=keep)

    def add_imu(self, stamp_ns: int, gyro_flu_radps: np.ndarray) -> None:
        self._add(self.imu, stamp_ns, gyro_flu_radps)

    def add_truth(self, stamp_ns: int, rates_flu_radps: np.ndarray) -> None:
        self._add(self.truth, stamp_ns, rates_flu_radps)

    def _add(self, buf: deque, stamp_ns: int, v: np.ndarray) -> None:
        if buf and stamp_ns <= buf[-1][0]:
            return
        buf.append((stamp_ns, np.asarray(v, float)))
        while buf[0][0] < stamp_ns - self.window_ns:
            buf.popleft()

    def lag_ms(self) -> float | None:
        """Measure over the current window; the median of the recent measurements (None: none yet)."""
        lag = self._measure()
        if lag is not None:
            self.measured.append(lag)
        return float(np.median(self.measured)) if self.measured else None

    def _measure(self) -> float | None:
        if len(self.imu) < 20 or len(self.truth) < 20:
            return None
        ti = np.array([t for t, _ in self.imu], float)
        gi = np.array([g for _, g in self.imu])
        tt = np.array([t for t, _ in self.truth], float)
        wt = np.array([w for _, w in self.truth])
        inside = (tt - self.lags_ns[-1] > ti[0]) & (tt - self.lags_ns[0] < ti[-1])
        tt, wt = tt[inside], wt[inside]
        if len(tt) < 20 or np.sqrt(np.mean(np.sum((wt - wt.mean(axis=0)) ** 2, axis=1))) < self.min_rate:
            return None
        # truth at stamp t is the IMU at t - lag: residual of each candidate lag
        cost = [np.mean(np.sum((np.column_stack([np.interp(tt - lag, ti, gi[:, k]) for k in range(3)]) - wt) ** 2,
                               axis=1)) for lag in self.lags_ns]
        best = int(np.argmin(cost))
        if 0 < best < len(cost) - 1:     # parabola through the minimum and its neighbours: sub-step
            c0, c1, c2 = cost[best - 1], cost[best], cost[best + 1]
            den = c0 - 2 * c1 + c2
            frac = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        else:
            frac = 0.0
        return float((self.lags_ns[best] + frac * (self.lags_ns[1] - self.lags_ns[0])) / 1e6)
