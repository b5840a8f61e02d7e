"""Process shell of vio: images + IMU from Zenoh -> strategy -> state/visual_odometry.

The strategy runs on a worker thread of its own, not in a subscriber callback: callbacks hold the
node lock and a 10-20 ms frame would stall the IMU, parameter and diagnostics callbacks. The
callbacks only pair left/right images by stamp into a one-frame slot (slot.py: newest wins, the
replaced frame is counted as dropped) and queue IMU samples.
"""
from __future__ import annotations

import ctypes
import functools
import threading
from collections import deque

import cv2
import numpy as np

from aeroperception.schemas import CameraInfo, DiagnosticStatus, Image, Imu, Reply, VioResetRequest
from aeroperception.services.runtime import CallError, Health, Service, run

from . import contract, messages
from .calibration import CalibrationError, CameraCalibration
from .config import VioServiceConfig
from .slot import FrameSlot, ImuWatermark
from .dto import (
    DEGRADED, INIT, LOST, STATE_NAMES, TRACKING, ImuWindow, NavCameraFrame, VioDegradedError,
    VioError, VioFatalError, VioInitializingError,
)
from .health import LOG_LEVEL
from .propagate import ImuPropagator
from .strategy import create_strategy

LEVEL = {INIT: DiagnosticStatus.WARN, TRACKING: DiagnosticStatus.OK, DEGRADED: DiagnosticStatus.WARN,
         LOST: DiagnosticStatus.ERROR}


class VioService(Service):
    """Stereo-inertial visual odometry (KLT + GTSAM fixed-lag smoother)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = VioServiceConfig

    def start(self) -> None:
        p = self.cfg
        if p.opencv_threads > 0:
            cv2.setNumThreads(p.opencv_threads)
        keep_freed_memory()
        self.strategy = create_strategy(p.strategy, p.strategy_config())   # unknown name: fails at start
        self.stereo = getattr(self.strategy, "stereo", True)
        self.infos: dict[str, CameraInfo | None] = {"left": None, "right": None}
        self.calib: CameraCalibration | None = None
        self.calib_error = ""
        self.frames = FrameSlot(self.stereo)
        self.imu_lock = threading.Lock()
        self.imu_pending: list = []
        self.imu_mark = ImuWatermark()
        self.counts = {"processed": 0, "errors": 0}
        self.timings: dict[str, deque] = {}
        self.last_out = None
        self.published_state: int | None = None
        self.pub_odom = self.io["state/visual_odometry"]
        self.odom_lock = threading.Lock()
        self.last_odom = (-1, 0)  # (reset_counter, stamp_ns) sent last: stamps only increase until a restart
        self.propagator = ImuPropagator(p.imu_noise(), p.imu_rate_hz, p.imu_rate_max_horizon_s) \
            if p.imu_rate_hz > 0 else None
        self.pub_health = self.io["state/vio_health"]
        for side in ("left", "right"):
            self.node.call_async(f"sensors/camera/{side}/info", None, CameraInfo, functools.partial(self._on_info_reply, side))
        self.pending_warm = None   # set by vio/srv/reset, applied by the worker before its next frame
        self.node.every(1.0, self._publish_health, name="health")
        self._stop = threading.Event()
        self.worker = threading.Thread(target=self._work, name="vio-worker", daemon=True)
        self.worker.start()
        self.log.info("vio_started", strategy=p.strategy, stereo=self.stereo)

    def stop(self) -> None:
        self._stop.set()
        self.frames.wake()
        self.worker.join(1.0)

    # ------------------------------------------------------------ inputs (callbacks)

    def on_sensors_camera_left_image(self, msg: Image) -> None:
        self.frames.put("left", msg, msg.header.stamp_ns)

    def on_sensors_camera_right_image(self, msg: Image) -> None:
        if self.stereo:
            self.frames.put("right", msg, msg.header.stamp_ns)

    def on_sensors_camera_left_info(self, msg: CameraInfo) -> None:
        self._on_info("left", msg)

    def on_sensors_camera_right_info(self, msg: CameraInfo) -> None:
        self._on_info("right", msg)

    def _on_info_reply(self, side: str, reply: CameraInfo | CallError) -> None:
        """The latched camera model asked for at start (on a call worker thread, not holding node.lock)."""
        if not isinstance(reply, CallError):
            self._on_info(side, reply)

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        old = self.infos[side]
        if old is not None and _same_info(old, msg):
            return
        self.infos[side] = msg
        left, right = self.infos["left"], self.infos["right"]
        if left is None or (self.stereo and right is None):
            return
        try:
            self.calib = CameraCalibration.from_camera_infos(left, right if self.stereo else None)
            self.calib_error = ""
            self.log.info("calibration", width=self.calib.width, height=self.calib.height,
                          baseline_m=round(self.calib.baseline_m, 4), focal_px=round(self.calib.f, 1))
        except (CalibrationError, ValueError) as e:
            self.calib, self.calib_error = None, str(e)
            self.log.throttled("error", "calib", "calibration_rejected", error=str(e))

    def on_sensors_imu(self, msg: Imu) -> None:
        sample = messages.imu_sample(msg)
        with self.imu_lock:
            self.imu_pending.append(sample)
        self.imu_mark.put(sample.t_ns)
        if self.propagator is not None and (out := self.propagator.on_imu(sample)) is not None:
            self._publish_odometry(out)

    def _publish_odometry(self, out) -> None:
        """Newest first: an output older than one already sent (a frame's estimate, stamped at its
        exposure, after IMU-propagated poses past it) is not sent; the propagator carries it forward.
        A re-initialisation (its reset_counter; e.g. after a replay's clock went back) starts over."""
        with self.odom_lock:
            counter, stamp = self.last_odom
            if out.reset_counter == counter and out.stamp_ns <= stamp:
                return
            self.last_odom = (out.reset_counter, out.stamp_ns)
        self.pub_odom.publish(messages.odometry(out))

    def on_vio_reset(self, req: VioResetRequest) -> Reply:
        try:
            warm = messages.warm_start(req)
        except ValueError as e:
            return Reply(success=False, message=f"vio/srv/reset refused: {e}")
        with self.imu_lock:
            self.pending_warm = warm
        self.frames.wake()
        p = warm.world_T_body[:3, 3]
        self.log.info("vio_reset_requested", position_m=[round(float(x), 3) for x in p])
        return Reply(success=True, message="restarting from the given pose: INIT until the next good stereo frame")

    # ------------------------------------------------------------ worker

    def _work(self) -> None:
        frame_id = 0
        while not self._stop.is_set():
            with self.imu_lock:
                warm, self.pending_warm = self.pending_warm, None
            if warm is not None:
                self.strategy.reset_to_warm_start(warm)
                if self.propagator is not None:
                    self.propagator.reset()
                self._publish_health()
            pair = self.frames.take(0.2)
            if pair is None:
                continue
            self.imu_mark.wait_for(pair[0].header.stamp_ns, self.cfg.imu_wait_s)
            with self.imu_lock:
                imu, self.imu_pending = self.imu_pending, []
            frame_id += 1
            left, right = pair
            t = left.header.stamp_ns
            frame = NavCameraFrame(frame_id, t, messages.pixels(left),
                                   messages.pixels(right) if right is not None else None)
            window = ImuWindow(imu[0].t_ns if imu else t, t, imu)
            try:
                out = self.strategy.process_frame(frame, window, self.calib)
            except VioDegradedError as e:
                out = e.output
            except (VioInitializingError, VioFatalError):
                out = None
            except VioError as e:
                out = None
                self.log.throttled("warn", "vio", "vio_error", error=str(e))
            except Exception as e:  # noqa: BLE001 - a bad frame must never stop the odometry
                out = None
                self.counts["errors"] += 1
                self.log.throttled("error", "vio", "frame_failed", error=f"{type(e).__name__}: {e}")
            self.counts["processed"] += 1
            if out is not None:
                self.last_out = out
                for k, v in out.timings_ms.items():
                    self.timings.setdefault(k, deque(maxlen=200)).append(v)
                if self.propagator is not None:
                    self.propagator.on_estimate(out)
                self._publish_odometry(out)
            elif self.propagator is not None and self.strategy.health_snapshot().state in (INIT, LOST):
                self.propagator.reset()      # restarting or lost: nothing to carry forward
            if self.strategy.health_snapshot().state != self.published_state:
                self._publish_health()

    def _publish_health(self) -> None:
        snap = self.strategy.health_snapshot()
        if self.calib is None:
            snap.message = self.calib_error or "waiting for camera calibration (sensors/camera/*/info)"
        out = self.last_out
        self.pub_health.publish(messages.health(
            snap, self.cfg.strategy, self.node.now_ns(), out.feature_quality if out else None,
            out.imu_bias if out else None))
        if snap.state != self.published_state:
            self.log.log(LOG_LEVEL[snap.state], "vio_state", state=STATE_NAMES[snap.state], message=snap.message)
        self.published_state = snap.state

    # ------------------------------------------------------------ diagnostics

    def health(self) -> Health:
        snap = self.strategy.health_snapshot()
        values: dict = {"state": STATE_NAMES[snap.state], "strategy": self.cfg.strategy,
                        "keyframes": getattr(self.strategy, "keyframes", 0), **self.counts,
                        "frames_in": self.frames.frames_in, "dropped_frames": self.frames.dropped,
                        "unpaired": self.frames.unpaired}
        values.update(getattr(self.strategy, "counters", {}))
        if self.propagator is not None:
            values.update(self.propagator.counters)
        values.update(imu_waits=self.imu_mark.waits, imu_wait_timeouts=self.imu_mark.timeouts)
        if self.last_out is not None:
            q = self.last_out.feature_quality
            values.update(tracked_features=q.tracked, inliers=q.inliers, consecutive_lost=snap.consecutive_lost,
                          bias_norm=round(snap.bias_norm, 4))
        for k, d in list(self.timings.items()):
            a = np.array(d)
            values[f"{k}_ms_p50"] = round(float(np.median(a)), 2)
            if k in ("frontend", "backend", "total"):
                values[f"{k}_ms_p99"] = round(float(np.percentile(a, 99)), 2)
        message = snap.message if self.calib is not None else (self.calib_error or "waiting for camera calibration")
        return Health(LEVEL[snap.state], f"{STATE_NAMES[snap.state]}: {message}", values)


def keep_freed_memory() -> None:
    """Let glibc's malloc keep large freed blocks for reuse instead of handing them back to the
    kernel. Every frame allocates and frees megabytes (two 921 KB payloads, the gray images, the
    pyramids and derivatives inside each optical-flow call): by default each such block is a fresh
    mmap or a heap grown after a trim, and every one of its pages faults again (~270 faults a frame,
    0.3-0.5 ms of kernel time, more on keyframes). The process keeps its peak instead (a few MB).
    No-op where the C library has no mallopt (not glibc)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 64 << 20)    # M_MMAP_THRESHOLD: blocks up to 64 MB from the heap, not mmap
        libc.mallopt(-1, 256 << 20)   # M_TRIM_THRESHOLD: return free heap top only beyond 256 MB
    except (OSError, AttributeError):
        pass


def _same_info(a: CameraInfo, b: CameraInfo) -> bool:
    return (a.width, a.height, a.distortion_model, a.T_body_camera) == (b.width, b.height, b.distortion_model, b.T_body_camera) \
        and np.array_equal(a.K.to_numpy(), b.K.to_numpy()) and np.array_equal(a.D.to_numpy(), b.D.to_numpy())


def main(argv=None) -> int:
    return run(VioService, argv)
