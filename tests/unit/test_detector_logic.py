"""The detector service's logic without Zenoh: hot swap through the model holder (bad models keep
the running one and report why), the health rule and the published form of detections."""
from __future__ import annotations


from detector_graphs import box_finder_model, classifier_model, paint_blocks

from aeroperception.schemas import DiagnosticStatus, Header
from aeroperception.services.detector import contract
from aeroperception.services.detector.logic import (
    PACKAGE_DIR, LoadRequest, ModelConfig, ModelHolder, StageTimes, detection_array, detector_health,
    resolve_model_path,
)
from aeroperception.services.runtime.config import build


def test_hot_swap_keeps_the_running_model_until_a_good_one_loads(tmp_path):
    good_a = box_finder_model(tmp_path / "a.onnx", names=["red", "green", "blue"])
    good_b = box_finder_model(tmp_path / "b.onnx", layout="channels_last", names=["r", "g", "b"])
    (tmp_path / "garbage.onnx").write_bytes(b"\x08\x07garbage" * 100)
    classifier = classifier_model(tmp_path / "cls.onnx")
    h = ModelHolder()
    assert not h.load(LoadRequest(str(tmp_path / "missing.onnx")))
    assert h.model is None and "model file not found" in h.error
    assert detector_health(h, StageTimes(), 10.0, 0.1, 2.0).level == DiagnosticStatus.ERROR

    assert h.load(LoadRequest(str(good_a))) and h.model.names == ["red", "green", "blue"] and h.error == ""
    assert h.load(LoadRequest(str(good_b))) and h.model.names == ["r", "g", "b"]
    running = h.model
    for bad, reason in [(tmp_path / "missing.onnx", "model file not found"),
                        (classifier, r"output shape [1, 1000] is not a YOLOv8"),
                        (tmp_path / "garbage.onnx", "not a loadable ONNX model")]:
        assert not h.load(LoadRequest(str(bad)))
        assert h.model is running and reason in h.error
        health = detector_health(h, StageTimes(), 10.0, 0.1, 2.0)   # the set was refused: b runs as named
        assert health.level == DiagnosticStatus.OK and "b.onnx" in health.message
        assert reason in health.values["model_refused"]
        dets, _ = h.model.detect(paint_blocks((480, 640), {1: (5, 5, 50, 50)}))
        assert [d[5] for d in dets] == [1]                     # the old model still detects
    assert h.load(LoadRequest(str(good_a))) and h.model.names[0] == "red" and h.error == ""
    assert detector_health(h, StageTimes(), 10.0, 0.1, 2.0).level == DiagnosticStatus.OK
    assert (h.swaps, h.failures) == (3, 4)


def test_load_request_from_parameters():
    assert build(ModelConfig, contract.PARAMS).request() == LoadRequest(contract.BUNDLED_MODEL, "", 1, None)
    req = build(ModelConfig, {**{x.name: x.default for x in contract.PARAMS},
                              "input_width": 320, "input_height": 256, "intra_op_threads": 2}).request()
    assert req.input_hw == (256, 320) and req.threads == 2


def test_relative_model_paths_fall_back_to_the_package(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert resolve_model_path(contract.BUNDLED_MODEL) == PACKAGE_DIR / contract.BUNDLED_MODEL
    (tmp_path / "mine.onnx").write_bytes(b"")
    assert resolve_model_path("mine.onnx") == tmp_path / "mine.onnx"


def test_health_warns_when_slower_than_the_rate_or_without_images(tmp_path):
    h = ModelHolder()
    h.load(LoadRequest(str(box_finder_model(tmp_path / "a.onnx"))))
    times = StageTimes()
    assert detector_health(h, times, 10.0, None, 2.0).message == "no camera image yet"
    assert detector_health(h, times, 10.0, 3.0, 2.0).level == DiagnosticStatus.WARN
    for _ in range(10):
        times.add({"pre": 5.0, "infer": 100.0, "post": 2.0})
    slow = detector_health(h, times, 10.0, 0.1, 2.0)
    assert slow.level == DiagnosticStatus.WARN and "107 ms is slower than the 10 Hz rate" in slow.message
    assert slow.values["infer_ms_p50"] == 100.0 and slow.values["total_ms_p99"] == 107.0
    assert detector_health(h, times, 5.0, 0.1, 2.0).level == DiagnosticStatus.OK


def test_detections_take_the_form_of_the_truth_boxes():
    msg = detection_array([(10.0, 20.0, 30.0, 60.0, 0.9, 2), (0.0, 0.0, 5.0, 5.0, 0.5, 7)], ["a", "b", "car"],
                          Header(stamp_ns=42, frame_id="camera_left_optical"), (480, 640))
    assert (msg.header.stamp_ns, msg.image_width, msg.image_height) == (42, 640, 480)
    d = msg.detections[0]
    assert (d.center_x_px, d.center_y_px, d.size_x_px, d.size_y_px, d.class_id, d.class_name, d.score) == \
        (20.0, 40.0, 20.0, 40.0, 2, "car", 0.9)
    assert msg.detections[1].class_name == "class_7"
