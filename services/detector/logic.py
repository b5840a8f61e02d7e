"""The detector's service logic without Zenoh: the model holder (hot swap), the rate gate, stage
timing and the health rule. The process shell (main.py) only wires these to keys.

Hot swap: a new model is loaded and test-run beside the one in use; only a model that works
replaces it. A model that does not (missing file, garbage bytes, not a YOLOv8 output) leaves the
running one in place and the reason in `error`; the service refuses the parameter set with it, so
the parameter keeps naming the model that runs (health: the reason in `model_refused`).
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from aeroperception.schemas import Detection2D, Detection2DArray, DiagnosticStatus, Header
from aeroperception.services.runtime import Health, param, section

from .yolo import Detection, ModelError, YoloModel

PACKAGE_DIR = Path(__file__).parent


def resolve_model_path(text: str, base: Path = PACKAGE_DIR) -> Path:
    """`~` expanded; a relative path is looked up in the working directory, then under `base`
    (the detector package, where the bundled model lives)."""
    p = Path(text).expanduser()
    if p.is_absolute():
        return p
    if p.exists():
        return Path.cwd() / p
    return base / p


@dataclass(frozen=True)
class LoadRequest:
    """Everything a model load depends on (ModelConfig.request: the model's parameters)."""

    model_path: str
    classes_file: str = ""
    threads: int = 1
    input_hw: tuple[int, int] | None = None
    provider: str = "cpu"


@dataclass(frozen=True)
class ModelConfig:
    """The parameters a model load depends on: a live change of one loads the new model beside
    the running one (swapped only if it works)."""

    model_path: str = param("model_path")
    classes_file: str = param("classes_file")
    intra_op_threads: int = param("intra_op_threads")
    input_width: int = param("input_width")
    input_height: int = param("input_height")
    execution_provider: str = param("execution_provider")

    def request(self) -> LoadRequest:
        hw = (self.input_height, self.input_width)
        return LoadRequest(model_path=self.model_path, classes_file=self.classes_file, threads=self.intra_op_threads,
                           input_hw=hw if all(hw) else None, provider=self.execution_provider)


@dataclass(frozen=True)
class DetectorConfig:
    """The detector's parameters (contract.PARAMS), rebuilt on a live change."""

    model: ModelConfig = section(ModelConfig)
    confidence_threshold: float = param("confidence_threshold")
    nms_threshold: float = param("nms_threshold")
    inference_frequency_hz: float = param("inference_frequency_hz")
    max_detections: int = param("max_detections")
    image_timeout_s: float = param("image_timeout_s")


class ModelHolder:
    """The model in use and the outcome of the last load. `load()` runs on a loader thread (the
    service's), `model` is read by the inference thread: one reference swap, never a gap."""

    def __init__(self, loader: Callable[..., YoloModel] = YoloModel.load):
        self._loader = loader
        self._lock = threading.Lock()
        self.model: YoloModel | None = None
        self.request: LoadRequest | None = None     # the one `model` was loaded from
        self.error = ""                               # why the last load failed; "" when it worked
        self.failed_request: LoadRequest | None = None
        self.swaps = 0
        self.failures = 0

    def load(self, req: LoadRequest) -> bool:
        """Load `req` beside the current model; swap on success. True when swapped."""
        path = resolve_model_path(req.model_path)
        classes = str(resolve_model_path(req.classes_file)) if req.classes_file else None
        try:
            new = self._loader(path, threads=req.threads, input_hw=req.input_hw, classes_file=classes,
                               provider=req.provider)
        except ModelError as e:
            with self._lock:
                self.error, self.failed_request = str(e), req
                self.failures += 1
            return False
        except Exception as e:  # noqa: BLE001 - any loader failure keeps the old model
            with self._lock:
                self.error, self.failed_request = f"{path}: {type(e).__name__}: {e}", req
                self.failures += 1
            return False
        with self._lock:
            self.model, self.request = new, req
            self.error, self.failed_request = "", None
            self.swaps += 1
        return True


class StageTimes:
    """Rolling per-stage times (ms) over the last `window` frames: pre, infer, post, total."""

    def __init__(self, window: int = 100):
        self.window = window
        self.ms: dict[str, deque[float]] = {}

    def add(self, times_ms: dict[str, float]) -> None:
        for k, v in times_ms.items():
            self.ms.setdefault(k, deque(maxlen=self.window)).append(v)
        self.ms.setdefault("total", deque(maxlen=self.window)).append(sum(times_ms.values()))

    def p50(self, stage: str) -> float | None:
        d = self.ms.get(stage)
        return float(np.percentile(d, 50)) if d else None

    def summary(self) -> dict[str, float]:
        out = {}
        for k, d in self.ms.items():
            if d:
                out[f"{k}_ms_p50"] = round(float(np.percentile(d, 50)), 2)
                out[f"{k}_ms_p99"] = round(float(np.percentile(d, 99)), 2)
        return out


def detection_array(dets: Sequence[Detection], names: Sequence[str], header: Header,
                    image_hw: tuple[int, int]) -> Detection2DArray:
    """Detections in the form sim/truth/boxes uses: centre + size in the image's pixels, COCO ids."""
    out = []
    for x1, y1, x2, y2, score, cls in dets:
        out.append(Detection2D(center_x_px=(x1 + x2) / 2, center_y_px=(y1 + y2) / 2, size_x_px=x2 - x1,
                               size_y_px=y2 - y1, class_id=int(cls),
                               class_name=names[cls] if 0 <= cls < len(names) else f"class_{cls}",
                               score=float(score)))
    return Detection2DArray(header=header, detections=out, image_width=int(image_hw[1]), image_height=int(image_hw[0]))


def detector_health(holder: ModelHolder, times: StageTimes, rate_hz: float,
                    image_age_s: float | None, image_timeout_s: float) -> Health:
    """Requirement DET-2: ERROR no (usable) model, WARN inference slower than the rate (or no camera
    images), else OK. A refused hot swap does not change the level: its set was refused, so the
    model that runs is the one the parameter names (the reason stays in `model_refused`)."""
    m = holder.model
    values: dict[str, object] = {"model_swaps": holder.swaps, "model_load_failures": holder.failures}
    if m is not None:
        values.update(model=m.path, input=f"{m.input_hw[1]}x{m.input_hw[0]}", classes=m.num_classes,
                      layout=m.layout, threads=m.threads, load_ms=round(m.load_ms, 1), execution_provider=m.provider)
    if holder.error:
        values["model_refused"] = holder.error
    values.update(times.summary())
    if m is None:
        return Health(DiagnosticStatus.ERROR, f"no model: {holder.error or 'none loaded'}", values)
    if image_age_s is None:
        return Health(DiagnosticStatus.WARN, "no camera image yet", values)
    if image_age_s > image_timeout_s:
        return Health(DiagnosticStatus.WARN, f"no camera image for {image_age_s:.1f} s", values)
    total = times.p50("total")
    if total is not None and total > 1e3 / rate_hz:
        return Health(DiagnosticStatus.WARN, f"inference {total:.0f} ms is slower than the {rate_hz:g} Hz rate", values)
    return Health(DiagnosticStatus.OK, f"{Path(m.path).name} {m.input_hw[1]}x{m.input_hw[0]}, {m.num_classes} classes",
                  values)
