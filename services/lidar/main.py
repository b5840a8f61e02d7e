"""Process shell: scans + vehicle pose in, obstacles / ground / costmap out.

Scans are processed on one worker thread, newest wins (runtime LatestWorker): a scan that
arrives while one is processed replaces the pending one and is counted as dropped, so a slow
machine lowers the output rate instead of growing a queue.
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np

from aeroperception.schemas import (
    DiagnosticStatus, Header, Imu, LandedState, NDArray, OccupancyGrid, PointCloud, Pose, Quaternion, SchemaError, Vector3,
    VehicleState,
)
from aeroperception.services.lib.pose_history import PoseHistory
from aeroperception.services.runtime import Health, LatestWorker, RateGate, Service, run
from aeroperception.services.runtime.rotations import quat_from_euler, quat_to_rotmat

from . import contract
from .config import LidarConfig
from .costmap import RollingCostmap
from .pipeline import ObstaclePipeline, ScanError

WORLD_FRAME = "map"


def gravity_levelling(f_body: np.ndarray) -> np.ndarray:
    """R_level_body from the measured specific force (points up at rest), yaw left at zero."""
    fx, fy, fz = f_body
    roll = math.atan2(fy, fz)
    pitch = math.atan2(-fx, math.hypot(fy, fz))
    return quat_to_rotmat(quat_from_euler(roll, pitch, 0.0))


class LidarService(Service):
    """LiDAR obstacle pipeline and rolling costmap (requirements LID-1 - LID-4)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = LidarConfig

    def start(self) -> None:
        self.pipeline = ObstaclePipeline(self.cfg.pipeline)
        self.costmap = RollingCostmap(self.cfg.costmap)
        self.poses = PoseHistory(horizon_s=2.0)
        self.gravity: np.ndarray | None = None
        self.refused = 0
        self.scans = 0
        self.no_pose = 0
        self.on_ground = False
        self.scans_on_ground = 0
        self.last_counts: dict[str, int] = {}
        self.timings: dict[str, deque[float]] = {}
        self.gate = RateGate(self.cfg.processing_rate_hz)
        self.last_ground_s = 0.0
        self.ground_found = False
        self.last_pose_ok = False
        self._config_lock = threading.Lock()
        self.pub_obstacles = self.io["perception/obstacles"]
        self.pub_ground = self.io["perception/ground"]
        self.pub_costmap = self.io["perception/costmap"]
        self.worker = LatestWorker(self._process, "lidar-scan", on_error=self._on_error)

    def stop(self) -> None:
        self.worker.stop()

    # ------------------------------------------------------------ inputs (node threads)

    def on_config(self, cfg: LidarConfig) -> None:
        self.gate.rate_hz = cfg.processing_rate_hz
        with self._config_lock:
            self.pipeline.cfg = cfg.pipeline
            new = cfg.costmap
            if (new.size_m, new.resolution_m) != (self.costmap.cfg.size_m, self.costmap.cfg.resolution_m):
                self.costmap = RollingCostmap(new)
            else:
                self.costmap.cfg = new

    def on_state_vehicle(self, msg: VehicleState) -> None:
        if not msg.connected:
            return
        self.on_ground = msg.landed_state == LandedState.ON_GROUND
        self.poses.add(msg)

    def on_sensors_imu(self, msg: Imu) -> None:
        f = msg.linear_acceleration_mps2.to_array()
        if np.all(np.isfinite(f)):
            self.gravity = f if self.gravity is None else 0.98 * self.gravity + 0.02 * f

    def on_sensors_lidar_points(self, msg: PointCloud) -> None:
        max_points = self.cfg.pipeline.max_points
        if len(msg) > max_points:      # garbage, not load: counted as invalid input
            self.node.report_bad_input("sensors/lidar/points", f"{len(msg)} points is more than max_points {max_points}")
            return
        # Thinned by the scans' own stamps, not their arrival times: scans at the processing rate
        # arrive with jitter under load (one 30 ms late, the next early), and an arrival-time
        # gap rule dropped every early one (costmap 8-9 Hz from 10 Hz scans).
        if not self.gate.admit(msg.header.stamp_ns * 1e-9):
            self.worker.dropped += 1
            return
        # The decoded array is a read-only view into the bytes the node copied the payload to
        # (not Zenoh's buffer): the worker can keep it without another 1.3 MB copy.
        self.worker.offer((msg.header.stamp_ns, msg.points.to_numpy()))

    # ------------------------------------------------------------ processing (worker thread)

    def _on_error(self, e: BaseException) -> None:
        if isinstance(e, (ScanError, SchemaError)):
            self.node.report_bad_input("sensors/lidar/points", str(e))
        else:
            self.node.callback_errors["lidar-scan"] += 1
            self.log.throttled("error", "scan", "scan_failed", error=f"{type(e).__name__}: {e}")

    def _process(self, item: tuple[int, np.ndarray]) -> None:
        cpu0 = time.thread_time()
        self._process_scan(*item)
        self.timings.setdefault("cpu", deque(maxlen=100)).append((time.thread_time() - cpu0) * 1e3)

    def _process_scan(self, stamp_ns: int, points: np.ndarray) -> None:
        """Pipeline, costmap and publication of one scan (the worker thread's CPU per scan is
        reported as cpu_ms_p50 / p99: what the CPU budget is spent on)."""
        cfg = self.cfg
        r_bs, t_bs = cfg.mount.body_sensor()
        pose = self.poses.nearest(stamp_ns, cfg.pose_max_age_s)
        if pose is not None:
            pos, r_wb = pose.position_m, pose.r_world_body
            r_level_sensor = r_wb @ r_bs
            sensor_offset = r_wb @ t_bs            # sensor relative to the vehicle, levelled axes
        else:
            self.no_pose += 1
            if self.gravity is None or not cfg.use_imu_tilt:
                r_level_body = np.eye(3)
            else:
                r_level_body = gravity_levelling(self.gravity)
            r_level_sensor, sensor_offset, pos = r_level_body @ r_bs, r_level_body @ t_bs, None
        with self._config_lock:
            res = self.pipeline.process(points, r_level_sensor, float(sensor_offset[2]))
            t0 = time.perf_counter()
            if pos is not None:
                origin = pos + sensor_offset
                cm = self.costmap
                cm.recenter(pos[0], pos[1])
                # On the ground the sensor is ~0.1 m above it: every return grazes the ground and
                # range noise reads as obstacles all around (6k false points per scan in the
                # village). The costmap is for flying: a landed vehicle's scans only clear.
                marks = res.obstacles
                if self.on_ground:
                    self.scans_on_ground += 1
                    marks = marks[:0]
                cm.update(origin[:2], marks, res.downsampled, res.ground)
                grid = cm.inflated()
                ox, oy = cm.origin_m
            res.timings_ms["costmap"] = (time.perf_counter() - t0) * 1e3
        self.scans += 1
        self.ground_found = res.plane.found
        self.last_pose_ok = pos is not None
        self.last_counts = res.counts
        for k, v in res.timings_ms.items():
            self.timings.setdefault(k, deque(maxlen=100)).append(v)
        self.timings.setdefault("total", deque(maxlen=100)).append(sum(res.timings_ms.values()))
        if pos is None:
            hdr = Header(stamp_ns=stamp_ns, frame_id="lidar_level")
            self.pub_obstacles.publish(PointCloud.from_numpy(res.obstacles, header=hdr))
            return
        hdr = Header(stamp_ns=stamp_ns, frame_id=WORLD_FRAME)
        self.pub_obstacles.publish(PointCloud.from_numpy(res.obstacles + origin.astype(np.float32), header=hdr))
        self.pub_costmap.publish(OccupancyGrid(
            header=hdr, resolution_m=cm.cfg.resolution_m, width=cm.n, height=cm.n,
            origin=Pose(position=Vector3(x=ox, y=oy, z=0.0), orientation=Quaternion()),
            data=NDArray.from_numpy(grid)))
        now = time.monotonic()
        if now - self.last_ground_s >= cfg.ground_publish_period_s:
            self.last_ground_s = now
            self.pub_ground.publish(PointCloud.from_numpy(res.ground + origin.astype(np.float32), header=hdr))

    # ------------------------------------------------------------ diagnostics

    def health(self) -> Health:
        values: dict[str, object] = {"scans": self.scans, "dropped": self.worker.dropped, "no_pose": self.no_pose,
                                     "scans_on_ground": self.scans_on_ground,
                                     "ground_found": self.ground_found, **self.last_counts}
        # The worker thread adds a stage's series when the stage first runs (some only in the air):
        # iterate a snapshot, taken atomically under the GIL, never the live dict or deques
        for k, d in list(self.timings.items()):
            if d := tuple(d):
                values[f"{k}_ms_p50"] = round(float(np.percentile(d, 50)), 2)
                values[f"{k}_ms_p99"] = round(float(np.percentile(d, 99)), 2)
        if self.scans == 0:
            return Health(DiagnosticStatus.WARN, "no scan processed yet", values)
        if not self.last_pose_ok:
            return Health(DiagnosticStatus.WARN, "no vehicle pose: obstacles in the levelled sensor frame only", values)
        if not self.ground_found:
            return Health(DiagnosticStatus.WARN, "no ground plane in the last scan (using the previous one)", values)
        return Health(DiagnosticStatus.OK, "ok", values)


def main(argv=None) -> int:
    return run(LidarService, argv)
