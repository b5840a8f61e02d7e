"""`aero bench detector`'s pieces: the YOLOv8n-sized graph really is YOLOv8n's size and emits a
YOLOv8 output the detector accepts, its score calibration gives the asked-for candidate count,
and the per-stage measurement runs the same YoloModel stages as the service."""
from __future__ import annotations

import numpy as np

from detector_graphs import box_finder_model, paint_blocks

from aeroperception.services.detector.yolo import YoloModel, letterbox
from aeroperception.tools.bench.detector import bench_model
from aeroperception.tools.training.yolov8n_graph import build, calibrate_scores


def test_yolov8n_sized_graph_has_yolov8n_cost_and_layout(tmp_path):
    info = build(tmp_path / "y.onnx", (320, 320), cls_bias=0.0)
    # Ultralytics reports YOLOv8n as 3.2 M parameters, 8.7 GFLOPs at 640 (a quarter at 320).
    assert 3.1e6 < info["params"] < 3.2e6 and abs(info["gflops"] * 4 - 8.7) < 0.1
    image = (np.random.default_rng(0).random((480, 640, 3)) * 255).astype(np.uint8)
    tensor, _ = letterbox(image, (320, 320), 32, channels="rgb")
    assert 45 <= calibrate_scores(tmp_path / "y.onnx", info["cls_convs"], tensor, candidates=50) <= 55
    m = YoloModel.load(tmp_path / "y.onnx")
    assert m.output_shape == (1, 84, 2100) and m.layout == "channels_first" and m.names[0] == "person"
    dets, _ = m.detect(image, channels="rgb")
    assert 0 < len(dets) <= 55


def test_bench_measures_every_stage_and_the_bare_run(tmp_path):
    r = bench_model(box_finder_model(tmp_path / "f.onnx"), 1, None, paint_blocks((480, 640), {0: (1, 2, 30, 40)}), 4)
    assert all(len(r[k]) == 4 and min(r[k]) > 0 for k in ("pre", "infer", "post", "total", "bare"))
    assert r["dets"] == 1 and r["input_hw"] == (640, 640)
