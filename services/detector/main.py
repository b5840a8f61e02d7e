"""Process shell: left camera images in, YOLOv8 detections out at <= inference_frequency_hz.

Frames above the rate are skipped at arrival (counted); an admitted frame that arrives while the
previous one is still being inferred replaces the pending one (runtime LatestWorker, counted as
dropped), so a slow machine lowers the output rate instead of growing a queue. A change of a
model parameter (logic.ModelConfig) loads the new model beside the one in use (logic.ModelHolder) before the
set is answered: a model that does not load refuses the set with the reason, the parameter keeps
the path that runs, and inference goes on with the old model meanwhile (it reads the holder, not
the parameter).
"""
from __future__ import annotations

import dataclasses
import time
from collections import deque
from pathlib import Path

import numpy as np

from aeroperception.schemas import Header, Image
from aeroperception.services.runtime import Health, LatestWorker, ParamError, RateGate, Service, run

from . import contract
from .logic import DetectorConfig, LoadRequest, ModelHolder, StageTimes, detection_array, detector_health

# Image encodings the detector reads, and the channel order letterbox() is told.
CHANNELS = {"rgb8": "rgb", "rgba8": "rgb", "bgr8": "bgr", "bgra8": "bgr", "mono8": "rgb", "mono16": "rgb",
            "16UC1": "rgb"}


class DetectorService(Service):
    """YOLOv8-format ONNX object detector (requirements DET-1 - DET-3)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = DetectorConfig

    def start(self) -> None:
        self.holder = ModelHolder()
        self.gate = RateGate(self.cfg.inference_frequency_hz)
        self.times = StageTimes()
        self.received = 0
        self.processed_without_model = 0
        self.last_image_s: float | None = None
        self.last_count = 0
        self.published_s: deque[float] = deque(maxlen=20)
        self.pub_dets = self.io["perception/detections"]
        self.pub_health = self.io["perception/detector_health"]
        self._load(self.cfg.model.request())        # the first model before the first frame
        self.worker = LatestWorker(self._process, "detector-infer", on_error=self._on_error)
        self.node.every(1.0, self._publish_health, name="health")

    def stop(self) -> None:
        self.worker.stop()

    # ------------------------------------------------------------ model loads

    def _load(self, req: LoadRequest) -> bool:
        if self.holder.load(req):
            m = self.holder.model
            self.log.info("model_loaded", path=m.path, input=f"{m.input_hw[1]}x{m.input_hw[0]}", classes=m.num_classes,
                          layout=m.layout, threads=m.threads, load_ms=round(m.load_ms, 1))
            return True
        self.log.error("model_refused", path=req.model_path, error=self.holder.error,
                       running=self.holder.model.path if self.holder.model else "none")
        return False

    def on_config(self, cfg: DetectorConfig) -> None:
        if cfg.model != self.cfg.model:
            # Loads while the set waits (node lock held: a frame callback waits too, inference does not).
            if not self._load(cfg.model.request()):
                m = self.holder.model
                running = f"still running {Path(m.path).name}" if m else "no model running"
                changed = [f.name for f in dataclasses.fields(cfg.model)
                           if getattr(cfg.model, f.name) != getattr(self.cfg.model, f.name)]
                raise ParamError(f"{', '.join(changed)}: model refused ({running}): {self.holder.error}")
        self.gate.rate_hz = cfg.inference_frequency_hz

    def _publish_health(self) -> None:
        self.pub_health.publish(self.node.diagnostics())

    # ------------------------------------------------------------ frames (node thread -> worker)

    def on_sensors_camera_left_image(self, msg: Image) -> None:
        self.received += 1
        self.last_image_s = time.monotonic()
        if msg.encoding not in CHANNELS:
            self.node.report_bad_input("sensors/camera/left/image", f"encoding {msg.encoding} is not supported "
                                       f"(use one of {', '.join(CHANNELS)})")
            return
        if not self.gate.admit(self.last_image_s):
            return
        # The decoded pixels are a view into Zenoh's buffer: copy before handing to the worker.
        pixels = np.array(msg.to_numpy())
        if pixels.dtype == np.uint16:
            pixels = (pixels >> 8).astype(np.uint8)
        self.worker.offer((msg.header, pixels, CHANNELS[msg.encoding]))

    def _on_error(self, e: BaseException) -> None:
        self.node.callback_errors["detector-infer"] += 1
        self.log.throttled("error", "infer", "inference_failed", error=f"{type(e).__name__}: {e}")

    def _process(self, item: tuple[Header, np.ndarray, str]) -> None:
        header, pixels, channels = item
        model = self.holder.model                      # one read: a swap mid-frame cannot mix models
        if model is None:
            self.processed_without_model += 1
            return
        p = self.cfg
        dets, times = model.detect(pixels, p.confidence_threshold, p.nms_threshold, channels, p.max_detections)
        self.times.add(times)
        self.pub_dets.publish(detection_array(dets, model.names, header, pixels.shape[:2]))
        self.last_count = len(dets)
        self.published_s.append(time.monotonic())

    # ------------------------------------------------------------ diagnostics

    def output_hz(self) -> float:
        t = self.published_s
        if len(t) < 2 or time.monotonic() - t[-1] > 2.0:
            return 0.0
        return (len(t) - 1) / (t[-1] - t[0])

    def health(self) -> Health:
        age = None if self.last_image_s is None else time.monotonic() - self.last_image_s
        h = detector_health(self.holder, self.times, self.cfg.inference_frequency_hz, age, self.cfg.image_timeout_s)
        h.values = {**(h.values or {}), "frames_received": self.received, "frames_skipped_rate": self.gate.skipped,
                    "frames_dropped_busy": self.worker.dropped, "frames_processed": self.worker.processed,
                    "frames_without_model": self.processed_without_model, "detections_last": self.last_count,
                    "output_hz": round(self.output_hz(), 2)}
        return h


def main(argv=None) -> int:
    return run(DetectorService, argv)
