"""The vehicle's recent poses (state/vehicle), so that a sensor sample is placed with the pose at
its own stamp, not with the pose the vehicle has when the sample is processed: a LiDAR scan
(lidar) and a camera frame's detections (objects).

Two ways to ask: `at` interpolates between the two samples around the stamp (position linearly,
attitude by normalised linear quaternion blend: the samples are a few ms apart) and `nearest`
takes the closest sample as it is. The history stays sorted by stamp: a duplicate or out-of-order
sample is ignored, and a clock that goes back by more than the horizon (a simulator restarted,
a replay started over) starts the history over instead of mixing two time lines. Thread-safe:
state/vehicle arrives on a node thread while a worker thread asks.
Frames: positions ENU (m), attitude q_enu_flu (w, x, y, z), rotating body FLU into world ENU.
"""
from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass

import numpy as np

from aeroperception.schemas import VehicleState
from aeroperception.services.runtime.rotations import quat_normalize, quat_to_rotmat


@dataclass(frozen=True)
class PoseSample:
    stamp_ns: int
    position_m: np.ndarray          # ENU
    q_enu_flu: np.ndarray           # (w, x, y, z)
    rate_radps: float = 0.0         # how fast the vehicle turns (its angular velocity's norm)

    @classmethod
    def of(cls, state: VehicleState) -> "PoseSample":
        return cls(state.header.stamp_ns, state.position_m.to_array(), state.orientation.to_array(),
                   float(np.linalg.norm(state.angular_velocity_radps.to_array())))

    @property
    def r_world_body(self) -> np.ndarray:
        """R_enu_flu: body vectors into the world frame."""
        return quat_to_rotmat(self.q_enu_flu)


class PoseHistory:
    """The last `horizon_s` of poses, sorted by stamp (see the module doc)."""

    def __init__(self, horizon_s: float = 3.0):
        self.horizon_ns = int(horizon_s * 1e9)
        self._stamps: list[int] = []
        self._samples: list[PoseSample] = []
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._samples)

    def add(self, state: VehicleState) -> None:
        """Remember the pose `state` reports at its stamp."""
        self.add_sample(PoseSample.of(state))

    def add_sample(self, s: PoseSample) -> None:
        with self._lock:
            if self._stamps and s.stamp_ns <= self._stamps[-1]:
                if s.stamp_ns < self._stamps[-1] - self.horizon_ns:
                    self._stamps.clear()            # the clock went back (sim restart): start over
                    self._samples.clear()
                else:
                    return                          # duplicate or out of order: the history stays sorted
            self._stamps.append(s.stamp_ns)
            self._samples.append(s)
            cut = bisect.bisect_left(self._stamps, s.stamp_ns - self.horizon_ns)
            if cut:
                del self._stamps[:cut], self._samples[:cut]

    def at(self, stamp_ns: int, tolerance_s: float) -> PoseSample | None:
        """The pose at `stamp_ns`, interpolated between the two samples around it (the faster of
        their turn rates); None when the stamp lies outside the history by more than `tolerance_s`
        or in a gap wider than twice it."""
        tol = int(tolerance_s * 1e9)
        with self._lock:
            s = self._samples
            if not s:
                return None
            i = bisect.bisect_left(self._stamps, stamp_ns)
            if i == 0:
                return s[0] if s[0].stamp_ns - stamp_ns <= tol else None
            if i == len(s):
                return s[-1] if stamp_ns - s[-1].stamp_ns <= tol else None
            a, b = s[i - 1], s[i]
        if b.stamp_ns - a.stamp_ns > 2 * tol:
            return None
        f = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        qb = b.q_enu_flu if np.dot(a.q_enu_flu, b.q_enu_flu) >= 0 else -b.q_enu_flu
        return PoseSample(stamp_ns, a.position_m + f * (b.position_m - a.position_m),
                          quat_normalize(a.q_enu_flu + f * (qb - a.q_enu_flu)), max(a.rate_radps, b.rate_radps))

    def nearest(self, stamp_ns: int, max_age_s: float) -> PoseSample | None:
        """The sample nearest `stamp_ns` as it is (its own stamp), None when none is within
        `max_age_s` of it."""
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp_ns)
            near = self._samples[max(0, i - 1):i + 1]
        if not near:
            return None
        best = min(near, key=lambda p: abs(p.stamp_ns - stamp_ns))
        return best if abs(best.stamp_ns - stamp_ns) <= max_age_s * 1e9 else None
