"""A YOLOv8n-sized ONNX graph with random weights, built with onnx.helper (no download, no torch).

Why: `aero bench detector` must measure a COCO-class YOLOv8n's cost on this machine, and the
weights are not ours to ship. The graph has YOLOv8n's layers and widths (Ultralytics yolov8.yaml,
scale n: depth 0.33, width 0.25; BatchNorm folded into the convolutions as in an export), its
Detect head with DFL decoding, and its output [1, 84, N] -- so FLOPs, memory traffic and the
post-processing input are those of the real model; only the boxes are meaningless.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

NC, REG_MAX = 80, 16


class _Graph:
    def __init__(self, seed: int, gain: float):
        self.gain = gain
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.rng = np.random.default_rng(seed)
        self.n = 0
        self.flops = 0.0
        self.params = 0

    def name(self, prefix: str) -> str:
        self.n += 1
        return f"{prefix}{self.n}"

    def const(self, value: np.ndarray, prefix: str = "c") -> str:
        n = self.name(prefix)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(value), n))
        return n

    def op(self, op_type: str, inputs: list[str], **attrs) -> str:
        out = self.name(op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], **attrs))
        return out

    def conv(self, x: str, c1: int, c2: int, k: int, s: int, hw: tuple[int, int], act: bool = True,
             bias: float = 0.0) -> tuple[str, tuple[int, int]]:
        """Conv2d (+ folded BN bias) + SiLU; returns output name and spatial size."""
        w = (self.rng.standard_normal((c2, c1, k, k)) * np.sqrt(self.gain / (c1 * k * k))).astype(np.float32)
        b = np.full(c2, bias, np.float32)
        out_hw = (hw[0] // s, hw[1] // s)
        self.flops += 2.0 * c1 * c2 * k * k * out_hw[0] * out_hw[1]
        self.params += w.size + b.size
        self.last_conv = (self.const(w, "w"), self.const(b, "b"))
        y = self.op("Conv", [x, *self.last_conv], kernel_shape=[k, k], strides=[s, s],
                    pads=[k // 2] * 4)
        if act:
            y = self.op("Mul", [y, self.op("Sigmoid", [y])])
        return y, out_hw

    def c2f(self, x: str, c1: int, c2: int, n: int, shortcut: bool, hw) -> str:
        c = c2 // 2
        y, _ = self.conv(x, c1, 2 * c, 1, 1, hw)
        a, b = self.name("split_a"), self.name("split_b")
        self.nodes.append(helper.make_node("Split", [y], [a, b], axis=1))
        parts = [a, b]
        for _ in range(n):
            t, _ = self.conv(parts[-1], c, c, 3, 1, hw)
            t, _ = self.conv(t, c, c, 3, 1, hw)
            parts.append(self.op("Add", [parts[-1], t]) if shortcut else t)
        out, _ = self.conv(self.op("Concat", parts, axis=1), (2 + n) * c, c2, 1, 1, hw)
        return out

    def sppf(self, x: str, c1: int, c2: int, hw) -> str:
        c = c1 // 2
        y, _ = self.conv(x, c1, c, 1, 1, hw)
        pools = [y]
        for _ in range(3):
            pools.append(self.op("MaxPool", [pools[-1]], kernel_shape=[5, 5], strides=[1, 1], pads=[2] * 4))
        out, _ = self.conv(self.op("Concat", pools, axis=1), 4 * c, c2, 1, 1, hw)
        return out

    def up(self, x: str) -> str:
        return self.op("Resize", [x, "", self.const(np.array([1, 1, 2, 2], np.float32), "scales")], mode="nearest")


def build(path: str | Path, input_hw: tuple[int, int] = (640, 640), cls_bias: float = -6.0, seed: int = 0,
          gain: float = 2.0) -> dict:
    """Write the graph to `path`; returns {"gflops", "params", "anchors"}."""
    g = _Graph(seed, gain)
    h, w = input_hw
    x = "images"
    x, s2 = g.conv(x, 3, 16, 3, 2, (h, w))
    x, s4 = g.conv(x, 16, 32, 3, 2, s2)
    x = g.c2f(x, 32, 32, 1, True, s4)
    x, s8 = g.conv(x, 32, 64, 3, 2, s4)
    p3 = g.c2f(x, 64, 64, 2, True, s8)
    x, s16 = g.conv(p3, 64, 128, 3, 2, s8)
    p4 = g.c2f(x, 128, 128, 2, True, s16)
    x, s32 = g.conv(p4, 128, 256, 3, 2, s16)
    x = g.c2f(x, 256, 256, 1, True, s32)
    p5 = g.sppf(x, 256, 256, s32)
    h12 = g.c2f(g.op("Concat", [g.up(p5), p4], axis=1), 384, 128, 1, False, s16)
    o3 = g.c2f(g.op("Concat", [g.up(h12), p3], axis=1), 192, 64, 1, False, s8)
    x, _ = g.conv(o3, 64, 64, 3, 2, s8)
    o4 = g.c2f(g.op("Concat", [x, h12], axis=1), 192, 128, 1, False, s16)
    x, _ = g.conv(o4, 128, 128, 3, 2, s16)
    o5 = g.c2f(g.op("Concat", [x, p5], axis=1), 384, 256, 1, False, s32)

    c2, c3 = max(16, 64 // 4, REG_MAX * 4), max(64, min(NC, 100))
    levels, anchors, strides, cls_convs = [], [], [], []
    for feat, ch, hw, stride in ((o3, 64, s8, 8), (o4, 128, s16, 16), (o5, 256, s32, 32)):
        a, _ = g.conv(feat, ch, c2, 3, 1, hw)
        a, _ = g.conv(a, c2, c2, 3, 1, hw)
        a, _ = g.conv(a, c2, 4 * REG_MAX, 1, 1, hw, act=False, bias=1.0)
        b, _ = g.conv(feat, ch, c3, 3, 1, hw)
        b, _ = g.conv(b, c3, c3, 3, 1, hw)
        b, _ = g.conv(b, c3, NC, 1, 1, hw, act=False, bias=cls_bias)
        cls_convs.append(g.last_conv)
        cat = g.op("Concat", [a, b], axis=1)
        levels.append(g.op("Reshape", [cat, g.const(np.array([1, 4 * REG_MAX + NC, -1], np.int64), "shape")]))
        ys, xs = np.meshgrid(np.arange(hw[0]) + 0.5, np.arange(hw[1]) + 0.5, indexing="ij")
        anchors.append(np.stack([xs.ravel(), ys.ravel()]))
        strides.append(np.full(hw[0] * hw[1], stride))
    allp = g.op("Concat", levels, axis=2)                                   # [1, 144, N]
    n_anchors = sum(a.shape[1] for a in anchors)
    box, cls = g.name("box"), g.name("cls")
    g.nodes.append(helper.make_node("Split", [allp, g.const(np.array([4 * REG_MAX, NC], np.int64))], [box, cls], axis=1))
    # DFL: softmax over 16 bins per side, expectation -> distances (l, t, r, b) in grid units.
    b4 = g.op("Reshape", [box, g.const(np.array([1, 4, REG_MAX, n_anchors], np.int64), "shape")])
    sm = g.op("Softmax", [b4], axis=2)
    dist = g.op("ReduceSum", [g.op("Mul", [sm, g.const(np.arange(REG_MAX, dtype=np.float32).reshape(1, 1, REG_MAX, 1))]),
                              g.const(np.array([2], np.int64), "axes")], keepdims=0)   # [1, 4, N]
    lt, rb = g.name("lt"), g.name("rb")
    g.nodes.append(helper.make_node("Split", [dist, g.const(np.array([2, 2], np.int64))], [lt, rb], axis=1))
    anc = g.const(np.concatenate(anchors, axis=1)[None].astype(np.float32), "anchors")
    x1y1, x2y2 = g.op("Sub", [anc, lt]), g.op("Add", [anc, rb])
    cxy = g.op("Mul", [g.op("Add", [x1y1, x2y2]), g.const(np.array(0.5, np.float32))])
    wh = g.op("Sub", [x2y2, x1y1])
    st = g.const(np.concatenate(strides)[None, None].astype(np.float32), "strides")
    xywh = g.op("Mul", [g.op("Concat", [cxy, wh], axis=1), st])
    g.nodes.append(helper.make_node("Concat", [xywh, g.op("Sigmoid", [cls])], ["output0"], axis=1))

    graph = helper.make_graph(g.nodes, "yolov8n_sized",
                              [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, h, w])],
                              [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 4 + NC, n_anchors])],
                              initializer=g.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    helper.set_model_props(model, {"stride": "32", "imgsz": f"[{h}, {w}]", "task": "detect",
                                   "description": "YOLOv8n-sized graph, random weights (aero bench detector)"})
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return {"gflops": g.flops / 1e9, "params": g.params, "anchors": n_anchors, "cls_convs": cls_convs}


def calibrate_scores(path: str | Path, cls_convs: list[tuple[str, str]], tensor: np.ndarray,
                     candidates: int = 50, conf: float = 0.40) -> int:
    """Rescale the class logits of a graph built with cls_bias=0 so that about `candidates`
    anchors score above `conf` on `tensor` (a trained model's typical count on a street scene),
    making the post-processing cost realistic. Rewrites `path`; returns the count reached."""
    import onnxruntime as ort

    p = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"images": tensor})[0][0, 4:]
    logits = np.log(p / (1.0 - p)).astype(np.float64)
    k = 2.0 / max(float(logits.std()), 1e-9)
    best = np.sort(k * logits.max(axis=0))[::-1]
    bias = float(np.log(conf / (1 - conf)) - (best[candidates - 1] + best[candidates]) / 2)
    model = onnx.load(str(path))
    by_name = {t.name: t for t in model.graph.initializer}
    for w_name, b_name in cls_convs:
        w = numpy_helper.to_array(by_name[w_name]) * np.float32(k)
        b = np.full(numpy_helper.to_array(by_name[b_name]).shape, bias, np.float32)
        by_name[w_name].CopyFrom(numpy_helper.from_array(w.astype(np.float32), w_name))
        by_name[b_name].CopyFrom(numpy_helper.from_array(b, b_name))
    onnx.save(model, str(path))
    q = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"images": tensor})[0][0, 4:]
    return int(np.count_nonzero(q.max(axis=0) > conf))
