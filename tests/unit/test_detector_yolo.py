"""The detector's plain logic (services/detector/yolo.py) against hand-built ONNX graphs:
letterbox + decode put boxes back at the right pixels of the original image (both output
layouts, several aspect ratios and input sizes), NMS is per class, thresholds are the seed's,
class names come from the model / a classes file / COCO, and non-YOLO models are refused
with a message naming what was found."""
from __future__ import annotations

import numpy as np
import pytest

from detector_graphs import box_finder_model, classifier_model, paint_blocks, planted_model

from aeroperception.services.detector.yolo import (
    LetterboxInfo, ModelError, YoloModel, coco_names, decode_yolov8, letterbox, letterbox_info, nms,
    parse_names_metadata, yolov8_layout,
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
