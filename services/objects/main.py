"""Process shell of the objects service: detections + stereo pair + vehicle pose in, tracked
objects out.

Detection frames go through a newest-wins slot (runtime LatestWorker): a frame that arrives while
the previous one is processed replaces the pending one and is counted as dropped, so the service
never queues behind the detector. Every other input only updates state (pose history, images by
stamp, calibration, home) under the node lock, which the worker takes while it places a frame.
"""
from __future__ import annotations

import functools
import time
from collections import deque

import numpy as np

from aeroperception.schemas import (
    CameraInfo, Detection2DArray, DiagnosticStatus, HomePosition, Image, ObjectEvent, VehicleState,
)
from aeroperception.services.runtime import CallError, Health, LatestWorker, Service, run

from . import contract
from .logic import ObjectsConfig, ObjectsPipeline

SIDES = ("left", "right")


class ObjectsService(Service):
    """Detections placed in the world and tracked (perception/objects)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = ObjectsConfig

    def start(self) -> None:
        node = self.node
        self.pipeline = ObjectsPipeline(self.cfg)
        self.frame_ms: deque[tuple[float, float]] = deque(maxlen=1000)   # (wall, CPU) per frame: minutes of a flight
        self.received = 0
        self.events_sent = {ObjectEvent.CONFIRMED: 0, ObjectEvent.LOST: 0, ObjectEvent.REACQUIRED: 0}
        self.pub_objects = self.io["perception/objects"]
        self.pub_events = self.io["perception/objects/events"]
        self.worker = LatestWorker(self._process, "objects-frame", on_error=self._on_error)
        for side in SIDES:
            node.call_async(f"sensors/camera/{side}/info", None, CameraInfo, functools.partial(self._on_info_reply, side))
        node.every(0.5, self._expire, name="expire")

    def stop(self) -> None:
        self.worker.stop()

    def on_config(self, cfg: ObjectsConfig) -> None:
        self.pipeline.reconfigure(cfg)

    # ------------------------------------------------------------ inputs (node lock held)

    def on_perception_detections(self, msg: Detection2DArray) -> None:
        self.received += 1
        self.worker.offer(msg)

    def on_state_vehicle(self, msg: VehicleState) -> None:
        self.pipeline.on_state(msg)

    def on_fmu_out_home_position(self, msg: HomePosition) -> None:
        self.pipeline.on_home(msg)

    def on_sensors_camera_left_image(self, msg: Image) -> None:
        self.pipeline.on_image("left", msg)

    def on_sensors_camera_right_image(self, msg: Image) -> None:
        self.pipeline.on_image("right", msg)

    def on_sensors_camera_left_info(self, msg: CameraInfo) -> None:
        self.pipeline.on_info("left", msg)

    def on_sensors_camera_right_info(self, msg: CameraInfo) -> None:
        self.pipeline.on_info("right", msg)

    def _on_info_reply(self, side: str, reply: CameraInfo | CallError) -> None:
        """The latched camera model asked for at start (a worker thread: taken like an input)."""
        if not isinstance(reply, CallError):
            self.node.run_callback(f"sensors/camera/{side}/info", self.pipeline.on_info, side, reply)

    def _on_error(self, e: BaseException) -> None:
        self.node.callback_errors["objects-frame"] += 1
        self.log.throttled("error", "frame", "frame_failed", error=f"{type(e).__name__}: {e}")

    def _process(self, msg: Detection2DArray) -> None:
        with self.node.lock:
            result = self.pipeline.process(msg)
        if result is None:
            return
        self.frame_ms.append((result.elapsed_ms, result.cpu_ms))
        self.pub_objects.publish(result.objects)
        self._send(result.events)

    def _expire(self) -> None:
        self._send(self.pipeline.expire(time.monotonic()))         # the timer holds the node lock

    def _send(self, events: list[ObjectEvent]) -> None:
        for e in events:
            self.pub_events.publish(e)
            self.events_sent[e.event] += 1
            o = e.object
            self.log.info(f"object_{e.event}", track_id=o.track_id, class_name=o.class_name, hits=o.hits,
                          position_m=[round(o.position_m.x, 2), round(o.position_m.y, 2), round(o.position_m.z, 2)])

    def health(self) -> Health:
        pl = self.pipeline
        ms = list(self.frame_ms)
        tracks = pl.tracker.tracks
        values = {
            "frames_received": self.received, "frames_processed": self.worker.processed,
            "frames_dropped_busy": self.worker.dropped,
            "tracks": len(tracks), "tracks_confirmed": sum(t.confirmed for t in tracks),
            **{f"events_{k}": n for k, n in self.events_sent.items()}, "tracks_lost_remembered": len(pl.tracker.lost),
            **{f"dropped[{k}]": n for k, n in pl.dropped.items()},
            **{f"placed[{k}]": n for k, n in pl.placed.items()},
            "home_known": pl.home is not None, "stereo_baseline_m": round(pl.camera.baseline_m, 3) if pl.camera else 0.0,
        }
        if ms:
            wall, cpu = np.array(ms).T
            values.update(frame_ms_p50=round(float(np.median(wall)), 2), frame_ms_max=round(float(wall.max()), 2),
                          frame_cpu_ms_p50=round(float(np.median(cpu)), 2),
                          frame_cpu_ms_p99=round(float(np.percentile(cpu, 99)), 2), frame_cpu_ms_max=round(float(cpu.max()), 2))
        if pl.camera is None:
            return Health(DiagnosticStatus.WARN, "waiting for camera calibration (sensors/camera/left/info)", values)
        if not pl.poses:
            return Health(DiagnosticStatus.WARN, "waiting for state/vehicle", values)
        return Health(DiagnosticStatus.OK, f"{values['tracks_confirmed']} confirmed tracks", values)


def main(argv=None) -> int:
    return run(ObjectsService, argv)
