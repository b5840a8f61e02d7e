"""YOLO ONNX detection as plain functions over numpy: letterbox, decode with class-aware NMS, class
names, and `YoloModel` (a validated onnxruntime session running the three stages).

Output layouts read: YOLOv8 / YOLO11 heads ([1, 4+nc, N] or [1, N, 4+nc]: cx, cy, w, h, class
scores; NMS here) and end-to-end exports (YOLO26, or any Ultralytics export with `nms=True`;
metadata `end2end: True` or args `nms: True`; [1, N, 6]: x1, y1, x2, y2, score, class, already
suppressed). Anything else is refused naming its shape.

Why one module without Zenoh: the detector service, `aero eval detector` and `aero bench detector`
must run the exact same pre- and post-processing, so an evaluation or a benchmark measures what
flies. Boxes are in the COCO/YOLO continuous pixel convention (the image spans [0, W] x [0, H]),
the one sim/truth/boxes uses. onnxruntime is imported only when a model is loaded.
"""
from __future__ import annotations

import ast
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

PAD_VALUE = 114                      # Ultralytics' letterbox grey
DEFAULT_STRIDE = 32
DEFAULT_INPUT_HW = (640, 640)        # for models exported with dynamic input axes
COCO_NAMES_FILE = Path(__file__).with_name("coco_classes.txt")
# execution_provider parameter -> ONNX Runtime's provider, and what it falls back to for operators
# it does not run (ONNX Runtime's own order: TensorRT, CUDA, CPU).
PROVIDERS = {
    "cpu": ("CPUExecutionProvider",),
    "cuda": ("CUDAExecutionProvider", "CPUExecutionProvider"),
    "tensorrt": ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
}

Detection = tuple[float, float, float, float, float, int]   # x1, y1, x2, y2 (original px), score, class_id


class ModelError(ValueError):
    """A model that cannot be used; the message is one line naming the reason (shape, path...)."""


# ------------------------------------------------------------------------------ letterbox


@dataclass(frozen=True)
class LetterboxInfo:
    """How an original image sits in the model input: model = original * scale + pad.

    `scale` is the uniform gain min(H_in / h, W_in / w); scale_x / scale_y are the exact per-axis
    gains after the resized size was rounded to whole pixels (they differ from `scale` by < 0.5 px
    over the image), used to map boxes back exactly. pad_x / pad_y: left / top padding (model px).
    """

    scale: float
    pad_x: int
    pad_y: int
    scale_x: float = 0.0
    scale_y: float = 0.0

    def gains(self) -> tuple[float, float]:
        return (self.scale_x or self.scale), (self.scale_y or self.scale)

    def to_original(self, xyxy: np.ndarray, original_hw: tuple[int, int] | None = None) -> np.ndarray:
        """Model-input boxes (N, 4) -> original-image boxes, clipped to the image when its size is given."""
        gx, gy = self.gains()
        out = np.asarray(xyxy, np.float64).reshape(-1, 4).copy()
        out[:, [0, 2]] = (out[:, [0, 2]] - self.pad_x) / gx
        out[:, [1, 3]] = (out[:, [1, 3]] - self.pad_y) / gy
        if original_hw is not None:
            h, w = original_hw
            out[:, [0, 2]] = out[:, [0, 2]].clip(0, w)
            out[:, [1, 3]] = out[:, [1, 3]].clip(0, h)
        return out

    def to_model(self, xyxy: np.ndarray) -> np.ndarray:
        """Original-image boxes (N, 4) -> model-input boxes (for training labels and tests)."""
        gx, gy = self.gains()
        out = np.asarray(xyxy, np.float64).reshape(-1, 4).copy()
        out[:, [0, 2]] = out[:, [0, 2]] * gx + self.pad_x
        out[:, [1, 3]] = out[:, [1, 3]] * gy + self.pad_y
        return out


def letterbox_info(original_hw: tuple[int, int], input_hw: tuple[int, int]) -> LetterboxInfo:
    """The resize + centred padding of Ultralytics' LetterBox (auto=False, scaleup=True)."""
    h, w = original_hw
    ih, iw = input_hw
    r = min(ih / h, iw / w)
    new_w, new_h = min(iw, max(1, int(round(w * r)))), min(ih, max(1, int(round(h * r))))
    pad_x = int(round((iw - new_w) / 2 - 0.1))
    pad_y = int(round((ih - new_h) / 2 - 0.1))
    return LetterboxInfo(scale=r, pad_x=pad_x, pad_y=pad_y, scale_x=new_w / w, scale_y=new_h / h)


def letterbox(image_bgr: np.ndarray, input_hw: Sequence[int], stride: int = DEFAULT_STRIDE, *,
              channels: str = "bgr") -> tuple[np.ndarray, LetterboxInfo]:
    """Image (H, W), (H, W, 3) or (H, W, 4) uint8 -> NCHW float32 RGB tensor in 0..1 of `input_hw`.

    The aspect ratio is kept (linear resize) and the rest padded with grey 114 around the centre.
    `channels` names the order of the given image ("bgr" as OpenCV reads, or "rgb" as the camera
    publishes); the tensor is always RGB, as YOLOv8 exports expect.
    """
    ih, iw = int(input_hw[0]), int(input_hw[1])
    if channels not in ("bgr", "rgb"):
        raise ValueError(f"channels must be 'bgr' or 'rgb', got {channels!r}")
    if ih % stride or iw % stride:
        raise ValueError(f"input size {ih}x{iw} is not a multiple of the model's stride {stride}")
    img = np.asarray(image_bgr)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.dtype != np.uint8 or min(img.shape[:2]) < 1:
        raise ValueError(f"expected a uint8 image (H, W[, 1|3|4]), got {img.dtype} {list(img.shape)}")
    if img.shape[2] == 4:
        img = img[:, :, :3]
    info = letterbox_info(img.shape[:2], (ih, iw))
    new_w = int(round(img.shape[1] * info.gains()[0]))
    new_h = int(round(img.shape[0] * info.gains()[1]))
    if (new_h, new_w) != img.shape[:2]:
        img = cv2.resize(np.ascontiguousarray(img), (new_w, new_h), interpolation=cv2.INTER_LINEAR)
        if img.ndim == 2:
            img = img[:, :, None]
    if img.shape[2] == 1:
        order = (0, 0, 0)                   # grey: the same plane in R, G and B
    else:
        order = (2, 1, 0) if channels == "bgr" else (0, 1, 2)
    tensor = np.full((1, 3, ih, iw), PAD_VALUE / 255.0, np.float32)
    y0, x0 = info.pad_y, info.pad_x
    for c_out, c_in in enumerate(order):
        np.multiply(img[:, :, c_in], np.float32(1 / 255.0), out=tensor[0, c_out, y0:y0 + new_h, x0:x0 + new_w],
                    casting="unsafe")
    return tensor, info


# ------------------------------------------------------------------------------ decode + NMS


def yolov8_layout(shape: Sequence[Any], num_classes: int | None = None) -> str:
    """"channels_first" for [1, 4+nc, N] (Ultralytics' export), "channels_last" for [1, N, 4+nc].

    Raises ModelError naming the shape for anything else (a classifier's [1, 1000], YOLOv5's
    objectness layout when the class count is known, a segmentation head...).
    """
    dims = list(shape)
    expected = "a YOLOv8 detection output [1, 4+nc, N] or [1, N, 4+nc]"
    if len(dims) != 3 or dims[0] != 1 or not all(isinstance(d, (int, np.integer)) for d in dims):
        raise ModelError(f"model output shape {dims} is not {expected}")
    a, b = int(dims[1]), int(dims[2])
    if num_classes is not None:
        c = 4 + int(num_classes)
        if a == c:
            return "channels_first"
        if b == c:
            return "channels_last"
        raise ModelError(f"model output shape {dims} is not {expected} with nc={num_classes} "
                         f"(no axis of size {c})")
    if min(a, b) < 5:
        raise ModelError(f"model output shape {dims} is not {expected} (needs at least 4 box values + 1 class)")
    return "channels_first" if a <= b else "channels_last"


END2END = "end2end"


def is_end2end_export(meta: dict[str, str]) -> bool:
    """Whether Ultralytics' export metadata says the output is already final boxes: `end2end`
    (YOLO26 and other NMS-free heads) or an export made with `nms=True` (args)."""
    if meta.get("end2end", "").strip().lower() == "true":
        return True
    try:
        args = ast.literal_eval(meta.get("args", "")) if meta.get("args") else {}
    except (ValueError, SyntaxError):
        return False
    return isinstance(args, dict) and args.get("nms") is True


def output_layout(shape: Sequence[Any], meta: dict[str, str], num_classes: int | None = None) -> str:
    """The output layout of a model with this output shape and export metadata: END2END for
    [1, N, 6] final boxes, else yolov8_layout's. ModelError naming the shape for anything else."""
    if not is_end2end_export(meta):
        return yolov8_layout(shape, num_classes)
    dims = list(shape)
    if len(dims) != 3 or dims[0] != 1 or dims[2] != 6:
        raise ModelError(f"model output shape {dims} is not an end-to-end detection output [1, N, 6] "
                         "(x1, y1, x2, y2, score, class), which its metadata (end2end / nms) announces")
    return END2END


def decode_end2end_array(output: np.ndarray, conf_thresh: float, info: LetterboxInfo,
                         original_hw: tuple[int, int], num_classes: int, max_det: int = 300) -> np.ndarray:
    """End-to-end output [1, N, 6] (x1, y1, x2, y2 in model-input pixels, score, class id) -> (K, 6)
    [x1, y1, x2, y2, score, class_id] in the original image's pixels, best first. The model has
    already suppressed duplicates (no NMS here); rows with a class id outside the model's classes
    are dropped."""
    rows = np.asarray(output, np.float64).reshape(-1, 6)
    cls = np.rint(rows[:, 5])
    rows = rows[(rows[:, 4] > conf_thresh) & (cls >= 0) & (cls < num_classes)]
    rows = rows[np.argsort(-rows[:, 4], kind="stable")[:max_det]]
    if len(rows) == 0:
        return np.zeros((0, 6))
    return np.column_stack([info.to_original(rows[:, :4], original_hw), rows[:, 4], np.rint(rows[:, 5])])


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou_thresh: float,
        class_ids: np.ndarray | None = None, max_keep: int | None = None) -> np.ndarray:
    """Greedy non-maximum suppression; indices kept, best first. With `class_ids`, boxes of
    different classes never suppress each other (each class is shifted to its own region)."""
    boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    if class_ids is not None:
        span = float(np.abs(boxes).max()) * 2.0 + 1.0
        boxes = boxes + (np.asarray(class_ids, np.float64) * span)[:, None]
    x1, y1, x2, y2 = boxes.T
    areas = np.maximum(x2 - x1, 0) * np.maximum(y2 - y1, 0)
    order = np.argsort(-np.asarray(scores), kind="stable")
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        if max_keep is not None and len(keep) >= max_keep:
            break
        rest = order[1:]
        iw = np.maximum(np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]), 0)
        ih = np.maximum(np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]), 0)
        inter = iw * ih
        iou = inter / np.maximum(areas[i] + areas[rest] - inter, 1e-12)
        order = rest[iou <= iou_thresh]
    return np.asarray(keep, np.int64)


def decode_yolov8_array(output: np.ndarray, conf_thresh: float, nms_thresh: float, info: LetterboxInfo,
                        original_hw: tuple[int, int], num_classes: int | None = None,
                        max_det: int = 300, max_candidates: int = 30000) -> np.ndarray:
    """Like decode_yolov8, as an (K, 6) float64 array [x1, y1, x2, y2, score, class_id]."""
    out = np.asarray(output)
    layout = yolov8_layout(out.shape, num_classes)
    pred = out[0] if layout == "channels_first" else out[0].T          # (4+nc, N), a view
    cls_scores = pred[4:]
    best = cls_scores.argmax(axis=0)
    score = cls_scores[best, np.arange(pred.shape[1])]
    idx = np.flatnonzero(score > conf_thresh)
    if idx.size > max_candidates:
        idx = idx[np.argsort(-score[idx], kind="stable")[:max_candidates]]
    if idx.size == 0:
        return np.zeros((0, 6))
    cx, cy, w, h = (pred[k, idx].astype(np.float64) for k in range(4))
    xyxy = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    keep = nms(xyxy, score[idx], nms_thresh, best[idx], max_keep=max_det)
    boxes = info.to_original(xyxy[keep], original_hw)
    return np.column_stack([boxes, score[idx][keep].astype(np.float64), best[idx][keep].astype(np.float64)])


def decode_yolov8(output: np.ndarray, conf_thresh: float, nms_thresh: float, info: LetterboxInfo,
                  original_hw: tuple[int, int], num_classes: int | None = None,
                  max_det: int = 300) -> list[Detection]:
    """YOLOv8 output [1, 4+nc, N] (or [1, N, 4+nc]) -> [(x1, y1, x2, y2, score, class_id)] in the
    original image's pixels, best first. Box rows are (cx, cy, w, h) in model-input pixels, then
    one score per class (already sigmoid-ed, no objectness). Score = the best class's, kept when
    > conf_thresh; NMS per class at IoU > nms_thresh. `num_classes` (when known) picks the axis
    exactly; without it the shorter axis is taken as the box+class one."""
    arr = decode_yolov8_array(output, conf_thresh, nms_thresh, info, original_hw, num_classes, max_det)
    return [(float(a), float(b), float(c), float(d), float(s), int(k)) for a, b, c, d, s, k in arr]


# ------------------------------------------------------------------------------ class names


def coco_names() -> list[str]:
    """The 80 COCO class names in YOLO order (shipped as coco_classes.txt)."""
    return load_class_names(COCO_NAMES_FILE)


def load_class_names(path: str | Path) -> list[str]:
    """A classes file: one name per line, in class-id order (blank lines at the end ignored)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise ModelError(f"classes file {p}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ModelError(f"classes file {p}: not UTF-8 text") from None
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise ModelError(f"classes file {p} has no names")
    return [ln.strip() for ln in lines]


def parse_names_metadata(text: str) -> list[str]:
    """Ultralytics' `names` metadata ("{0: 'person', 1: 'bicycle'}", or a list literal) -> list."""
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        raise ModelError(f"model metadata 'names' is not a dict or list literal: {text[:60]!r}") from None
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    if isinstance(value, dict) and all(isinstance(k, int) and k >= 0 for k in value):
        n = max(value) + 1 if value else 0
        return [str(value.get(i, f"class_{i}")) for i in range(n)]
    raise ModelError(f"model metadata 'names' is not a dict of class id -> name: {text[:60]!r}")


def model_metadata(session) -> dict[str, str]:
    """The ONNX model's custom metadata (Ultralytics writes names, stride, imgsz, task...)."""
    try:
        return dict(session.get_modelmeta().custom_metadata_map)
    except Exception:  # noqa: BLE001 - a model without metadata simply has none
        return {}


def class_names_from_model(session, classes_file: str | Path | None = None,
                           num_classes: int | None = None) -> list[str]:
    """Names by class id: the model's `names` metadata, else `classes_file`, else COCO's for an
    80-class model, else class_<i>. When `num_classes` is given the count must match."""
    meta = model_metadata(session)
    if "names" in meta:
        names, source = parse_names_metadata(meta["names"]), "model metadata 'names'"
    elif classes_file:
        names, source = load_class_names(classes_file), f"classes file {classes_file}"
    elif num_classes == 80:
        names, source = coco_names(), "COCO names"
    else:
        return [f"class_{i}" for i in range(num_classes or 0)]
    if num_classes is not None and len(names) != num_classes:
        raise ModelError(f"{source} has {len(names)} names but the model outputs {num_classes} classes")
    return names


# ------------------------------------------------------------------------------ the model


@dataclass
class YoloModel:
    """An onnxruntime session checked to be a YOLOv8 detector: its input size, stride, output
    layout and class names known. `load` runs a test inference, so a model that loads is one
    that runs."""

    session: Any
    path: str
    input_name: str
    input_hw: tuple[int, int]
    input_dtype: Any
    stride: int
    layout: str
    output_shape: tuple[int, ...]
    names: list[str]
    threads: int = 1
    load_ms: float = 0.0
    metadata: dict[str, str] = field(default_factory=dict)
    provider: str = "cpu"                # the execution provider the session runs on

    @property
    def num_classes(self) -> int:
        return len(self.names)

    @classmethod
    def load(cls, path: str | Path, threads: int = 1, input_hw: tuple[int, int] | None = None,
             classes_file: str | Path | None = None, provider: str = "cpu") -> "YoloModel":
        """Open and validate on `provider` (a PROVIDERS name); raises ModelError with a one-line
        reason, for a provider this onnxruntime lacks or cannot start too."""
        t0 = time.perf_counter()
        p = Path(path)
        if not p.is_file():
            raise ModelError(f"model file not found: {p}")
        try:
            import onnxruntime as ort
        except ImportError:
            raise ModelError("onnxruntime is not installed: run deploy/install.sh with the perception extra") from None
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.log_severity_level = 3
        # Idle worker threads must not spin on a 2-core machine shared with the control path.
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        chain = session_providers(provider, ort.get_available_providers())
        try:
            session = ort.InferenceSession(str(p), so, providers=list(chain))
        except Exception as e:  # noqa: BLE001 - onnxruntime raises several types for bad files
            raise ModelError(f"{p}: not a loadable ONNX model ({_first_line(e)})") from None
        if session.get_providers()[0] != chain[0]:
            # ONNX Runtime falls back to the next provider when one fails to start (missing CUDA
            # libraries): running on something else than asked must not pass unseen.
            raise ModelError(f"execution provider {provider} ({chain[0]}) failed to start: the session runs on "
                             f"{session.get_providers()[0]} (check the CUDA / TensorRT libraries)")
        inputs = session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(f"{p}: expected one image input, the model has {len(inputs)}")
        inp = inputs[0]
        shape = list(inp.shape)
        if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
            raise ModelError(f"{p}: input shape {shape} is not an NCHW 3-channel image [1, 3, H, W]")
        dtypes = {"tensor(float)": np.float32, "tensor(float16)": np.float16}
        if inp.type not in dtypes:
            raise ModelError(f"{p}: input type {inp.type} is not float32/float16")
        meta = model_metadata(session)
        try:
            stride = int(meta.get("stride", DEFAULT_STRIDE))
        except ValueError:
            stride = DEFAULT_STRIDE
        fixed = tuple(d if isinstance(d, int) and d > 0 else None for d in shape[2:])
        if input_hw and any(input_hw):
            if all(fixed) and tuple(input_hw) != fixed:
                raise ModelError(f"{p}: input is fixed at {fixed[0]}x{fixed[1]}; the input size override "
                                 f"{input_hw[0]}x{input_hw[1]} needs a model exported with dynamic axes")
            hw = (int(input_hw[0]), int(input_hw[1]))
        else:
            exported = _imgsz(meta.get("imgsz", "")) or DEFAULT_INPUT_HW     # dynamic axes: the export's size
            hw = (fixed[0] or exported[0], fixed[1] or exported[1])
        if hw[0] % stride or hw[1] % stride:
            raise ModelError(f"{p}: input size {hw[0]}x{hw[1]} is not a multiple of the stride {stride}")
        dummy = np.full((1, 3, *hw), PAD_VALUE / 255.0, dtypes[inp.type])
        try:
            outs = session.run(None, {inp.name: dummy})
        except Exception as e:  # noqa: BLE001
            raise ModelError(f"{p}: test inference at {hw[0]}x{hw[1]} failed ({_first_line(e)})") from None
        out_shape = tuple(int(d) for d in np.shape(outs[0]))
        meta_nc = len(parse_names_metadata(meta["names"])) if "names" in meta else None
        try:
            layout = output_layout(out_shape, meta, meta_nc)
        except ModelError as e:
            raise ModelError(f"{p}: {e}") from None
        if layout == END2END:
            names = class_names_from_model(session, classes_file or None)
            if not names:
                raise ModelError(f"{p}: an end-to-end output carries no class count: give classes_file")
        else:
            nc = (out_shape[1] if layout == "channels_first" else out_shape[2]) - 4
            names = class_names_from_model(session, classes_file or None, nc)
        return cls(session=session, path=str(p), input_name=inp.name, input_hw=hw, input_dtype=dtypes[inp.type],
                   stride=stride, layout=layout, output_shape=out_shape, names=names, threads=int(threads),
                   load_ms=(time.perf_counter() - t0) * 1e3, metadata=meta, provider=provider)

    # The three stages, separately timed by callers (service diagnostics, bench).

    def preprocess(self, image: np.ndarray, channels: str = "bgr") -> tuple[np.ndarray, LetterboxInfo]:
        tensor, info = letterbox(image, self.input_hw, self.stride, channels=channels)
        return (tensor if self.input_dtype is np.float32 else tensor.astype(self.input_dtype)), info

    def infer(self, tensor: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input_name: tensor})[0]

    def postprocess(self, output: np.ndarray, info: LetterboxInfo, original_hw: tuple[int, int],
                    conf_thresh: float, nms_thresh: float, max_det: int = 300) -> list[Detection]:
        """Boxes in the original image; `nms_thresh` applies to YOLOv8-layout heads only (an
        end-to-end model has suppressed its duplicates itself)."""
        if self.layout == END2END:
            arr = decode_end2end_array(output, conf_thresh, info, original_hw, self.num_classes, max_det)
            return [(float(a), float(b), float(c), float(d), float(sc), int(k)) for a, b, c, d, sc, k in arr]
        return decode_yolov8(output, conf_thresh, nms_thresh, info, original_hw, self.num_classes, max_det)

    def detect(self, image: np.ndarray, conf_thresh: float = 0.40, nms_thresh: float = 0.45,
               channels: str = "bgr", max_det: int = 300) -> tuple[list[Detection], dict[str, float]]:
        """Image -> detections in its pixels, and the stage times in ms (pre, infer, post)."""
        t0 = time.perf_counter()
        tensor, info = self.preprocess(image, channels)
        t1 = time.perf_counter()
        out = self.infer(tensor)
        t2 = time.perf_counter()
        dets = self.postprocess(out, info, image.shape[:2], conf_thresh, nms_thresh, max_det)
        t3 = time.perf_counter()
        return dets, {"pre": (t1 - t0) * 1e3, "infer": (t2 - t1) * 1e3, "post": (t3 - t2) * 1e3}


def session_providers(provider: str, available: Sequence[str]) -> tuple[str, ...]:
    """ONNX Runtime providers for the `execution_provider` name `provider`: the asked one first,
    then its fallbacks this onnxruntime has. ModelError naming what exists when it is unknown or
    not in this onnxruntime."""
    have = [name for name, chain in PROVIDERS.items() if chain[0] in available]
    if provider not in PROVIDERS:
        raise ModelError(f"execution provider {provider!r} is unknown (one of {', '.join(PROVIDERS)}; "
                         f"this onnxruntime has {', '.join(have)})")
    chain = PROVIDERS[provider]
    if chain[0] not in available:
        raise ModelError(f"execution provider {provider} ({chain[0]}) is not in this onnxruntime: it has "
                         f"{', '.join(have)} ({', '.join(available)}); install onnxruntime-gpu for cuda/tensorrt")
    return tuple(c for c in chain if c in available)


def _imgsz(text: str) -> tuple[int, int] | None:
    """Ultralytics' `imgsz` metadata ("[640, 640]") -> (h, w), None when absent or unreadable."""
    try:
        v = ast.literal_eval(text) if text else None
    except (ValueError, SyntaxError):
        return None
    if isinstance(v, int):
        v = [v, v]
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, int) and x > 0 for x in v):
        return int(v[0]), int(v[1])
    return None


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return (text[0] if text else type(e).__name__)[:200]
