"""How well fmu's streams line up in time, free of Zenoh: camera frames against the IMU stream
(requirement SIM-1, only with publish_imu) and the VIO pipeline's latency (exposure -> ODOMETRY
sent: what EKF2_EV_DELAY would have to be without PX4's time sync). Reported in diagnostics."""
from __future__ import annotations

import math
from collections import deque

import numpy as np


class StreamTiming:
    def __init__(self) -> None:
        self.imu_stamps_ns: deque[int] = deque(maxlen=400)      # recent sensors/imu stamps (2 s)
        self.vio_age_ms: deque[float] = deque(maxlen=100)       # exposure -> ODOMETRY sent
        self.camera_imu_dt_ms: deque[float] = deque(maxlen=50)  # image stamp - newest IMU stamp before it

    def on_imu(self, stamp_ns: int) -> None:
        self.imu_stamps_ns.append(stamp_ns)

    def on_image(self, stamp_ns: int) -> float:
        """How far (ms) a camera frame is from the last IMU sample at or before it (the first one
        when none is before it; NaN without IMU): large or negative = clock or driver trouble."""
        if not self.imu_stamps_ns:
            dt_ms = math.nan
        else:
            before = [t for t in self.imu_stamps_ns if t <= stamp_ns]
            dt_ms = (stamp_ns - (before[-1] if before else self.imu_stamps_ns[0])) / 1e6
        self.camera_imu_dt_ms.append(dt_ms)
        return dt_ms

    def on_vio_sent(self, age_s: float) -> None:
        self.vio_age_ms.append(age_s * 1000.0)

    def values(self) -> dict[str, float]:
        """The diagnostics figures (only those measured)."""
        out: dict[str, float] = {}
        if self.camera_imu_dt_ms:
            dts = np.array(self.camera_imu_dt_ms)
            out["camera_imu_dt_p50_ms"] = round(float(np.nanmedian(dts)), 3)
            out["camera_imu_dt_max_ms"] = round(float(np.nanmax(np.abs(dts))), 3)
        if self.vio_age_ms:
            ages = np.array(self.vio_age_ms)
            out["vio_age_p50_ms"] = round(float(np.median(ages)), 1)
            out["vio_age_max_ms"] = round(float(ages.max()), 1)
        return out
