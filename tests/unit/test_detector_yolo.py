"""The detector's plain logic (services/detector/yolo.py) against hand-built ONNX graphs:
letterbox + decode put boxes back at the right pixels of the original image (both output
layouts, several aspect ratios and input sizes), NMS is per class, thresholds are requirement DET-1's,
class names come from the model / a classes file / COCO, and non-YOLO models are refused
with a message naming what was found."""
from __future__ import annotations

import numpy as np
import pytest

from detector_graphs import box_finder_model, classifier_model, paint_blocks, planted_model

from aeroperception.services.detector.yolo import (
    END2END, LetterboxInfo, ModelError, YoloModel, coco_names, decode_yolov8, letterbox, letterbox_info, nms,
    parse_names_metadata, session_providers, yolov8_layout,
)

LAYOUTS = ("channels_first", "channels_last")
# (height, width) of original images: landscape VGA, HD (downscaled 2x), portrait, small square
# (upscaled), very wide, and odd sizes that make the padding uneven.
ASPECTS = [(480, 640), (720, 1280), (640, 480), (300, 300), (250, 1000), (333, 517)]


def _blocks(hw):
    h, w = hw
    return {0: (10, 20, min(w, 110), min(h, 90)),                  # near the top-left corner
            1: (w - 60, h - 50, w, h),                             # touching the bottom-right edges
            2: (w // 2 - 33, h // 2 - 17, w // 2 + 41, h // 2 + 29)}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("input_hw", [(640, 640), (320, 480)])
def test_blocks_found_by_the_graph_come_back_at_their_pixels(tmp_path, layout, input_hw):
    """The graph locates the blocks in the letterboxed tensor; decoding maps them back to within
    1 px of where they were painted (exact when the image is not downscaled; at most one original
    pixel per model pixel when it is)."""
    model = YoloModel.load(box_finder_model(tmp_path / "finder.onnx", input_hw, layout), threads=1)
    assert model.layout == layout and model.names == ["red", "green", "blue"] and model.input_hw == input_hw
    for hw in ASPECTS:
        blocks = _blocks(hw)
        for channels in ("rgb", "bgr"):
            dets, times = model.detect(paint_blocks(hw, blocks, channels), channels=channels)
            assert sorted(d[5] for d in dets) == [0, 1, 2], (hw, dets)
            info = letterbox_info(hw, input_hw)
            tol = max(1.0, 1.0 / min(info.gains())) if min(info.gains()) < 0.5 else 1.0
            for x1, y1, x2, y2, score, cls in dets:
                err = np.abs(np.array([x1, y1, x2, y2]) - blocks[cls])
                assert err.max() <= tol + 1e-6, (hw, input_hw, cls, err)
                assert score == pytest.approx(0.9, abs=1e-6)
            assert set(times) == {"pre", "infer", "post"}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("hw", ASPECTS)
def test_planted_boxes_decode_exactly(tmp_path, layout, hw):
    """Boxes planted in model pixels (computed here from Ultralytics' letterbox definition) come
    back as the original-image boxes they came from, to 1e-3 px."""
    input_hw = (640, 640)
    h, w = hw
    r = min(input_hw[0] / h, input_hw[1] / w)
    new_w, new_h = round(w * r), round(h * r)
    pad_x, pad_y = round((input_hw[1] - new_w) / 2 - 0.1), round((input_hw[0] - new_h) / 2 - 0.1)
    truth = np.array([[0, 0, w * 0.25, h * 0.4], [w * 0.5, h * 0.5, w, h], [w * 0.1, h * 0.6, w * 0.3, h * 0.9]])
    sx, sy = new_w / w, new_h / h
    m = truth * [sx, sy, sx, sy] + [pad_x, pad_y, pad_x, pad_y]
    rows = np.zeros((12, 4 + 3), np.float32)   # more anchors than channels, as in real models
    rows[:3, :4] = np.column_stack([(m[:, 0] + m[:, 2]) / 2, (m[:, 1] + m[:, 3]) / 2, m[:, 2] - m[:, 0], m[:, 3] - m[:, 1]])
    rows[0, 4], rows[1, 5], rows[2, 6] = 0.95, 0.8, 0.6
    rows[3:5, :4] = [320, 320, 50, 50]
    rows[3, 4] = 0.39                                                # below the 0.40 threshold
    model = YoloModel.load(planted_model(tmp_path / "p.onnx", rows, layout, input_hw), threads=1)
    dets, _ = model.detect(np.zeros((h, w, 3), np.uint8))
    assert [d[5] for d in dets] == [0, 1, 2] and [round(d[4], 3) for d in dets] == [0.95, 0.8, 0.6]
    np.testing.assert_allclose(np.array([d[:4] for d in dets]), truth, atol=1e-3)
    assert model.names == ["class_0", "class_1", "class_2"]          # no metadata, no classes file


def _rows(boxes_xyxy, scores, classes, nc=3):
    b = np.asarray(boxes_xyxy, float)
    rows = np.zeros((len(b), 4 + nc), np.float32)
    rows[:, :4] = np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2, b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]])
    rows[np.arange(len(b)), 4 + np.asarray(classes)] = scores
    return rows


IDENTITY = LetterboxInfo(scale=1.0, pad_x=0, pad_y=0)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_nms_is_class_aware(layout):
    a, b = [100, 100, 200, 200], [110, 100, 210, 200]                  # IoU 0.82
    far = [400, 400, 450, 450]
    rows = _rows([a, b, a, b, far, [100, 100, 200, 200]], [0.9, 0.8, 0.7, 0.85, 0.5, 0.41], [0, 0, 1, 1, 0, 2])
    out = rows.T[None] if layout == "channels_first" else rows[None]
    dets = decode_yolov8(out, 0.40, 0.45, IDENTITY, (640, 640), num_classes=3)
    got = [(d[5], round(d[4], 2)) for d in dets]
    # class 0: a suppresses b; class 1: b (0.85) suppresses a (0.7); far and class 2 untouched.
    assert got == [(0, 0.9), (1, 0.85), (0, 0.5), (2, 0.41)]
    np.testing.assert_allclose(dets[1][:4], b)


def test_nms_keeps_boxes_below_the_iou_threshold():
    boxes = np.array([[0, 0, 100, 100], [50, 0, 150, 100], [60, 0, 160, 100]], float)   # IoU(0,1) = 1/3
    keep = nms(boxes, np.array([0.9, 0.8, 0.7]), 0.45)
    assert keep.tolist() == [0, 1]                                      # 2 overlaps 1 at IoU 0.82
    assert nms(boxes, np.array([0.9, 0.8, 0.7]), 0.45, class_ids=np.array([0, 1, 2])).tolist() == [0, 1, 2]


def test_confidence_threshold_is_strict_and_boxes_are_clipped():
    rows = _rows([[-20, -10, 50, 60], [10, 10, 20, 20]], [0.401, 0.40], [0, 1])
    dets = decode_yolov8(rows.T[None], 0.40, 0.45, IDENTITY, (100, 200), num_classes=3)
    assert len(dets) == 1 and dets[0][:4] == (0.0, 0.0, 50.0, 60.0)


@pytest.mark.parametrize("shape", [(1, 1000), (1, 84, 8400, 1), (2, 84, 8400), (1, 3, 4), (1, 4, 2)])
def test_non_yolov8_shapes_are_refused_naming_the_shape(shape):
    with pytest.raises(ModelError, match=str(list(shape)).replace("[", r"\[").replace("]", r"\]")):
        yolov8_layout(shape)


def test_layout_with_known_class_count():
    assert yolov8_layout((1, 84, 8400), 80) == "channels_first"
    assert yolov8_layout((1, 8400, 84), 80) == "channels_last"
    assert yolov8_layout((1, 7, 5), 3) == "channels_first"     # fewer anchors than channels: nc decides
    assert yolov8_layout((1, 5, 7), 3) == "channels_last"
    with pytest.raises(ModelError, match=r"\[1, 85, 8400\].*nc=80"):
        yolov8_layout((1, 85, 8400), 80)                        # YOLOv5 (objectness) with 80 names


def test_letterbox_pads_grey_and_keeps_aspect():
    img = np.full((480, 640, 3), 255, np.uint8)
    img[:, :, 0] = 0                                                  # BGR: blue channel 0 -> RGB "yellow"
    t, info = letterbox(img, (640, 640), 32)
    assert t.shape == (1, 3, 640, 640) and t.dtype == np.float32
    assert (info.pad_x, info.pad_y, info.scale) == (0, 80, 1.0)
    assert np.allclose(t[0, :, :80], 114 / 255) and np.allclose(t[0, :, 560:], 114 / 255)
    assert np.allclose(t[0, 0, 80:560], 1.0) and np.allclose(t[0, 2, 80:560], 0.0)   # R=1, B=0
    grey, _ = letterbox(np.full((100, 50), 200, np.uint8), (64, 64), 32)
    assert np.allclose(grey[0, :, :, 16:48], 200 / 255)
    with pytest.raises(ValueError, match="multiple of the model's stride 32"):
        letterbox(img, (600, 640), 32)


def test_info_maps_both_ways():
    info = letterbox_info((333, 517), (640, 640))
    b = np.array([[12.5, 7.25, 300.0, 333.0]])
    np.testing.assert_allclose(info.to_original(info.to_model(b)), b)


def test_class_names_from_metadata_file_and_coco(tmp_path):
    assert parse_names_metadata("{0: 'person', 2: 'car'}") == ["person", "class_1", "car"]
    assert parse_names_metadata("['a', 'b']") == ["a", "b"]
    with pytest.raises(ModelError, match="names"):
        parse_names_metadata("import os")
    rows = np.zeros((100, 84), np.float32)
    coco = YoloModel.load(planted_model(tmp_path / "coco.onnx", rows))
    assert coco.names == coco_names() and coco.names[0] == "person" and len(coco.names) == 80
    (tmp_path / "mine.txt").write_text("drone\nbird\nkite\n\n")
    three = planted_model(tmp_path / "three.onnx", np.zeros((8, 7), np.float32))
    assert YoloModel.load(three, classes_file=tmp_path / "mine.txt").names == ["drone", "bird", "kite"]
    (tmp_path / "two.txt").write_text("a\nb\n")
    with pytest.raises(ModelError, match="2 names but the model outputs 3 classes"):
        YoloModel.load(three, classes_file=tmp_path / "two.txt")
    named = planted_model(tmp_path / "named.onnx", np.zeros((8, 7), np.float32), names=["x", "y", "z"])
    assert YoloModel.load(named, classes_file=tmp_path / "mine.txt").names == ["x", "y", "z"]   # metadata first


def test_coco_names_file_matches_the_simulators_class_ids():
    from aeroperception.services.sim.world.scenario import COCO_CLASSES

    assert tuple(coco_names()) == COCO_CLASSES


def test_bad_models_are_refused_with_the_reason(tmp_path):
    with pytest.raises(ModelError, match="model file not found"):
        YoloModel.load(tmp_path / "nope.onnx")
    (tmp_path / "garbage.onnx").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ModelError, match="not a loadable ONNX model"):
        YoloModel.load(tmp_path / "garbage.onnx")
    with pytest.raises(ModelError, match=r"output shape \[1, 1000\] is not a YOLOv8"):
        YoloModel.load(classifier_model(tmp_path / "cls.onnx"))


def test_input_size_from_the_model_or_the_override(tmp_path):
    dyn = box_finder_model(tmp_path / "dyn.onnx", input_hw=None)
    assert YoloModel.load(dyn).input_hw == (640, 640)
    exported = box_finder_model(tmp_path / "imgsz.onnx", input_hw=None, imgsz=(384, 512))
    assert YoloModel.load(exported).input_hw == (384, 512)             # Ultralytics' imgsz metadata
    odd_stride = box_finder_model(tmp_path / "s64.onnx", input_hw=None, stride=64)
    with pytest.raises(ModelError, match="not a multiple of the stride 64"):
        YoloModel.load(odd_stride, input_hw=(352, 352))               # fine for stride 32
    m = YoloModel.load(dyn, input_hw=(320, 416))
    assert m.input_hw == (320, 416)
    dets, _ = m.detect(paint_blocks((480, 640), {0: (100, 100, 200, 180)}, "bgr"))
    assert len(dets) == 1 and np.abs(np.array(dets[0][:4]) - [100, 100, 200, 180]).max() <= 1.0
    with pytest.raises(ModelError, match="not a multiple of the stride 32"):
        YoloModel.load(dyn, input_hw=(300, 300))
    fixed = box_finder_model(tmp_path / "fixed.onnx", input_hw=(640, 640))
    with pytest.raises(ModelError, match="fixed at 640x640"):
        YoloModel.load(fixed, input_hw=(320, 320))
    assert YoloModel.load(fixed, input_hw=(640, 640)).input_hw == (640, 640)


# ------------------------------------------------------------------ YOLO11, YOLO26 (end-to-end), providers

YOLO11_META = {"description": "Ultralytics YOLO11n model trained on coco.yaml", "task": "detect", "end2end": "False",
               "args": "{'batch': 1, 'half': False, 'nms': False}"}


def test_yolo11_export_reads_like_yolov8(tmp_path):
    """YOLO11's head has YOLOv8's output layout: [1, 4+nc, N], NMS on our side."""
    model = YoloModel.load(box_finder_model(tmp_path / "y11.onnx", metadata=YOLO11_META))
    assert model.layout == "channels_first"
    blocks = _blocks((480, 640))
    dets, _ = model.detect(paint_blocks((480, 640), blocks, "rgb"), channels="rgb")
    assert sorted(d[5] for d in dets) == [0, 1, 2]
    for x1, y1, x2, y2, _, cls in dets:
        assert np.abs(np.array([x1, y1, x2, y2]) - blocks[cls]).max() <= 1.0


@pytest.mark.parametrize("input_hw", [(640, 640), (320, 480)])
def test_yolo26_end_to_end_export_finds_the_blocks_at_their_pixels(tmp_path, input_hw):
    """An end-to-end graph ([1, N, 6]: x1, y1, x2, y2, score, class; metadata end2end) locates the
    blocks in the letterboxed tensor; they come back where they were painted."""
    model = YoloModel.load(box_finder_model(tmp_path / "y26.onnx", input_hw, layout="end2end"))
    assert model.layout == END2END and model.output_shape == (1, 8, 6) and model.names == ["red", "green", "blue"]
    for hw in ASPECTS:
        blocks = _blocks(hw)
        dets, _ = model.detect(paint_blocks(hw, blocks, "bgr"), channels="bgr")
        assert sorted(d[5] for d in dets) == [0, 1, 2], (hw, dets)
        info = letterbox_info(hw, input_hw)
        tol = max(1.0, 1.0 / min(info.gains())) if min(info.gains()) < 0.5 else 1.0
        for x1, y1, x2, y2, score, cls in dets:
            assert np.abs(np.array([x1, y1, x2, y2]) - blocks[cls]).max() <= tol + 1e-6, (hw, cls)
            assert score == pytest.approx(0.9, abs=1e-6)


def test_end_to_end_rows_decode_best_first_without_nms(tmp_path):
    rows = np.array([
        [100, 100, 200, 300, 0.70, 0],
        [102, 101, 201, 299, 0.65, 0],      # overlaps the first: the model kept both, so do we
        [300, 300, 400, 400, 0.90, 1],
        [10, 10, 20, 20, 0.30, 1],          # below the 0.40 threshold
        [10, 10, 20, 20, 0.95, 7],          # a class the model does not have
        [0, 0, 0, 0, 0.0, 0],               # padding rows of a fixed-size output
    ], np.float32)
    path = planted_model(tmp_path / "e2e.onnx", rows, "channels_last", names=["person", "car"],
                         metadata={"end2end": "True"})
    model = YoloModel.load(path)
    assert model.layout == END2END
    dets, _ = model.detect(np.zeros((640, 640, 3), np.uint8), conf_thresh=0.4, nms_thresh=0.1)
    assert [(d[5], round(d[4], 2)) for d in dets] == [(1, 0.9), (0, 0.7), (0, 0.65)]
    np.testing.assert_allclose(dets[0][:4], [300, 300, 400, 400], atol=1e-3)
    assert len(model.detect(np.zeros((640, 640, 3), np.uint8), max_det=2)[0]) == 2


def test_an_export_made_with_nms_reads_as_end_to_end(tmp_path):
    rows = np.array([[50, 60, 150, 260, 0.8, 1]], np.float32)
    path = planted_model(tmp_path / "nms.onnx", rows, "channels_last", names=["a", "b"],
                         metadata={"args": "{'batch': 1, 'nms': True, 'conf': 0.25}"})
    model = YoloModel.load(path)
    assert model.layout == END2END
    assert [d[5] for d in model.detect(np.zeros((640, 640, 3), np.uint8))[0]] == [1]


def test_unknown_layouts_are_still_refused_by_name(tmp_path):
    v8_rows = np.zeros((12, 7), np.float32)
    with pytest.raises(ModelError, match=r"output shape \[1, 12, 7\] is not an end-to-end detection output \[1, N, 6\]"):
        YoloModel.load(planted_model(tmp_path / "liar.onnx", v8_rows, "channels_last", metadata={"end2end": "True"}))
    with pytest.raises(ModelError, match="end-to-end output carries no class count: give classes_file"):
        YoloModel.load(planted_model(tmp_path / "anon.onnx", np.zeros((4, 6), np.float32), "channels_last",
                                     metadata={"end2end": "True"}))
    classes = tmp_path / "classes.txt"
    classes.write_text("person\ncar\n")
    assert YoloModel.load(tmp_path / "anon.onnx", classes_file=classes).names == ["person", "car"]
    with pytest.raises(ModelError, match=r"output shape \[1, 1000\] is not a YOLOv8"):
        YoloModel.load(classifier_model(tmp_path / "cls.onnx"))


def test_execution_provider_defaults_to_cpu_and_absent_ones_are_refused_by_name(tmp_path):
    import onnxruntime as ort

    path = box_finder_model(tmp_path / "f.onnx")
    assert YoloModel.load(path).provider == "cpu"
    with pytest.raises(ModelError, match=r"execution provider 'npu' is unknown \(one of cpu, cuda, tensorrt; this onnxruntime has cpu"):
        YoloModel.load(path, provider="npu")
    if "TensorrtExecutionProvider" not in ort.get_available_providers():
        with pytest.raises(ModelError, match=r"execution provider tensorrt \(TensorrtExecutionProvider\) is not in this "
                                             r"onnxruntime: it has cpu.*install onnxruntime-gpu"):
            YoloModel.load(path, provider="tensorrt")


def test_provider_chains_fall_back_only_to_what_is_there():
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert session_providers("tensorrt", gpu) == tuple(gpu)
    assert session_providers("cuda", gpu) == ("CUDAExecutionProvider", "CPUExecutionProvider")
    assert session_providers("cpu", gpu) == ("CPUExecutionProvider",)
    with pytest.raises(ModelError, match="it has cpu, cuda"):
        session_providers("tensorrt", ["CUDAExecutionProvider", "CPUExecutionProvider"])


def test_a_provider_change_the_runtime_lacks_keeps_the_running_model(tmp_path):
    import onnxruntime as ort
    from aeroperception.services.detector.logic import LoadRequest, ModelHolder

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    h = ModelHolder()
    path = str(box_finder_model(tmp_path / "f.onnx"))
    assert h.load(LoadRequest(path))
    running = h.model
    assert not h.load(LoadRequest(path, provider="cuda"))
    assert h.model is running and "execution provider cuda (CUDAExecutionProvider) is not in this onnxruntime" in h.error


def test_bench_says_which_provider_ran_and_refuses_an_absent_one(tmp_path, capsys):
    import onnxruntime as ort
    from aeroperception.tools.bench.detector import bench_model, run

    r = bench_model(box_finder_model(tmp_path / "f.onnx"), 1, None, paint_blocks((480, 640), {0: (1, 2, 30, 40)}), 2)
    assert r["provider"] == "CPUExecutionProvider"
    if "TensorrtExecutionProvider" not in ort.get_available_providers():
        assert run(n=1, provider="tensorrt") == 2
        assert "execution provider tensorrt (TensorrtExecutionProvider) is not in this onnxruntime" in capsys.readouterr().err
