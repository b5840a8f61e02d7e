"""Hand-built ONNX graphs for the detector's tests (onnx.helper, no weights, no download).

- `planted_model`: emits fixed YOLOv8 rows (boxes in model-input pixels + class scores).
- `box_finder_model`: a real "detector" of solid colour blocks: per RGB channel it finds the
  extent of the pixels brighter than 0.5 in the letterboxed input and reports it as a YOLOv8
  box of class = channel (red 0, green 1, blue 2). Boxes come out where the pixels really are
  after letterboxing, so decoding them back proves the whole geometry, not just its algebra.
  With layout "end2end" it answers like a YOLO26 (NMS-free) export: [1, anchors, 6] rows of
  x1, y1, x2, y2, score, class and `end2end: True` in the metadata.
- `classifier_model`: a valid ONNX whose output [1, 1000] is no YOLOv8 layout.
- `metadata` (planted_model, box_finder_model): extra export metadata, e.g. a YOLO11 description.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 13


def _save(graph: onnx.GraphProto, path: Path, names: Sequence[str] | None, stride: int | None = None,
          imgsz: tuple[int, int] | None = None, metadata: dict[str, str] | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    meta = dict(metadata or {})
    if names is not None:
        meta["names"] = repr({i: n for i, n in enumerate(names)})
    if stride is not None:
        meta["stride"] = str(stride)
    if imgsz is not None:
        meta["imgsz"] = str(list(imgsz))
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path


def _input(input_hw: tuple[int, int] | None) -> onnx.ValueInfoProto:
    h, w = input_hw if input_hw else ("height", "width")
    return helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, h, w])


def planted_model(path: Path, rows: np.ndarray, layout: str = "channels_first",
                  input_hw: tuple[int, int] = (640, 640), names: Sequence[str] | None = None,
                  metadata: dict[str, str] | None = None) -> Path:
    """rows: (N, 4 + nc) = cx, cy, w, h (model px), class scores. Output [1, 4+nc, N] or [1, N, 4+nc]
    (channels_last also plants end-to-end rows (N, 6) as [1, N, 6])."""
    rows = np.asarray(rows, np.float32)
    const = rows.T[None] if layout == "channels_first" else rows[None]
    nodes = [
        # output = const + 0 * mean(images): the graph depends on its input like a real model
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Add", ["planted", "z"], ["output0"]),
    ]
    graph = helper.make_graph(
        nodes, "planted", [_input(input_hw)],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(const.shape))],
        initializer=[numpy_helper.from_array(np.ascontiguousarray(const), "planted"),
                     numpy_helper.from_array(np.zeros((), np.float32), "zero")])
    return _save(graph, path, names, metadata=metadata)


def box_finder_model(path: Path, input_hw: tuple[int, int] | None = (640, 640), layout: str = "channels_first",
                     names: Sequence[str] | None = ("red", "green", "blue"), anchors: int = 8,
                     stride: int | None = None, imgsz: tuple[int, int] | None = None,
                     metadata: dict[str, str] | None = None) -> Path:
    """See the module docstring. input_hw None: dynamic height/width axes (imgsz: the size
    Ultralytics records in the metadata of such an export)."""
    assert anchors >= 3
    f = TensorProto.FLOAT
    nodes = [
        helper.make_node("Greater", ["images", "thr"], ["mask_b"]),
        helper.make_node("Cast", ["mask_b"], ["mask"], to=f),
        helper.make_node("ReduceMax", ["mask"], ["cols"], axes=[2], keepdims=0),     # [1, 3, W]
        helper.make_node("ReduceMax", ["mask"], ["rows"], axes=[3], keepdims=0),     # [1, 3, H]
        helper.make_node("ReduceMax", ["cols"], ["present"], axes=[2], keepdims=0),  # [1, 3]
    ]
    for name, prof in (("x", "cols"), ("y", "rows")):
        nodes += [
            helper.make_node("ArgMax", [prof], [f"{name}1_i"], axis=2, keepdims=0, select_last_index=0),
            helper.make_node("ArgMax", [prof], [f"{name}2_i"], axis=2, keepdims=0, select_last_index=1),
            helper.make_node("Cast", [f"{name}1_i"], [f"{name}1"], to=f),
            helper.make_node("Cast", [f"{name}2_i"], [f"{name}2l"], to=f),
            helper.make_node("Add", [f"{name}2l", "one"], [f"{name}2"]),                # last pixel + 1
            helper.make_node("Add", [f"{name}1", f"{name}2"], [f"{name}s"]),
            helper.make_node("Mul", [f"{name}s", "half"], [f"c{name}"]),
            helper.make_node("Sub", [f"{name}2", f"{name}1"], [f"s{name}"]),
        ]
    for v in ("cx", "cy", "sx", "sy"):
        nodes.append(helper.make_node("Unsqueeze", [v, "ax1"], [f"{v}_u"]))                # [1, 1, 3]
    nodes += [
        helper.make_node("Concat", ["cx_u", "cy_u", "sx_u", "sy_u"], ["boxes"], axis=1),  # [1, 4, 3]
        helper.make_node("Mul", ["present", "score"], ["sc"]),
        helper.make_node("Unsqueeze", ["sc", "ax1"], ["sc_u"]),                            # [1, 1, 3]
        helper.make_node("Mul", ["sc_u", "eye"], ["cls"]),                                 # [1, 3, 3]
        helper.make_node("Concat", ["boxes", "cls"], ["found"], axis=1),                   # [1, 7, 3]
        helper.make_node("Concat", ["found", "empty"], ["first"], axis=2),                 # [1, 7, anchors]
    ]
    out_shape = [1, 7, anchors]
    if layout == "end2end":
        for v in ("x1", "y1", "x2", "y2", "sc"):
            nodes.append(helper.make_node("Unsqueeze", [v, "ax2"], [f"{v}_e"]))             # [1, 3, 1]
        nodes += [
            helper.make_node("Concat", ["x1_e", "y1_e", "x2_e", "y2_e", "sc_e", "cls_ids"], ["e2e_rows"], axis=2),
            helper.make_node("Concat", ["e2e_rows", "empty_e2e"], ["output0"], axis=1),         # [1, anchors, 6]
        ]
        out_shape = [1, anchors, 6]
        metadata = {"end2end": "True", **(metadata or {})}
    elif layout == "channels_first":
        nodes.append(helper.make_node("Identity", ["first"], ["output0"]))
    else:
        nodes.append(helper.make_node("Transpose", ["first"], ["output0"], perm=[0, 2, 1]))
        out_shape = [1, anchors, 7]
    init = [
        numpy_helper.from_array(np.array(0.5, np.float32), "thr"),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array(0.5, np.float32), "half"),
        numpy_helper.from_array(np.array(0.9, np.float32), "score"),
        numpy_helper.from_array(np.array([1], np.int64), "ax1"),
        numpy_helper.from_array(np.eye(3, dtype=np.float32)[None], "eye"),
        numpy_helper.from_array(np.zeros((1, 7, anchors - 3), np.float32), "empty"),
        numpy_helper.from_array(np.array([2], np.int64), "ax2"),
        numpy_helper.from_array(np.arange(3, dtype=np.float32).reshape(1, 3, 1), "cls_ids"),
        numpy_helper.from_array(np.zeros((1, anchors - 3, 6), np.float32), "empty_e2e"),
    ]
    graph = helper.make_graph(nodes, "box_finder", [_input(input_hw)],
                              [helper.make_tensor_value_info("output0", f, out_shape)], initializer=init)
    return _save(graph, path, names, stride, imgsz, metadata)


def classifier_model(path: Path, classes: int = 1000) -> Path:
    """An image classifier: [1, 3, 64, 64] -> [1, classes] (valid ONNX, not a detector)."""
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["pooled"], axes=[2, 3], keepdims=0),   # [1, 3]
        helper.make_node("MatMul", ["pooled", "w"], ["logits"]),
    ]
    graph = helper.make_graph(
        nodes, "classifier", [_input((64, 64))],
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, classes])],
        initializer=[numpy_helper.from_array(np.ones((3, classes), np.float32), "w")])
    return _save(graph, path, None)


def paint_blocks(hw: tuple[int, int], blocks: dict[int, tuple[int, int, int, int]], channels: str = "rgb") -> np.ndarray:
    """A black uint8 image with solid blocks: {class (0 red, 1 green, 2 blue): (x1, y1, x2, y2)}
    covering pixels [x1, x2) x [y1, y2); channel order as named."""
    img = np.zeros((*hw, 3), np.uint8)
    for cls, (x1, y1, x2, y2) in blocks.items():
        ch = cls if channels == "rgb" else 2 - cls
        img[y1:y2, x1:x2, ch] = 255
    return img
