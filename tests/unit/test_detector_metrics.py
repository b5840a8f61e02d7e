"""The detection metric (services/detector/metrics.py) against hand-computed cases."""
import math

import numpy as np
import pytest

from aeroperception.services.detector.metrics import DetectionEval, average_precision, format_table, iou_matrix


def test_iou_matrix_hand_values():
    a = np.array([[0, 0, 10, 10]])
    b = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 5, 5]])
    np.testing.assert_allclose(iou_matrix(a, b), [[1.0, 50 / 150, 0.0, 0.25]])
    assert iou_matrix(np.zeros((0, 4)), b).shape == (0, 4)


def test_average_precision_all_point_interpolation():
    # 3 truths; ranked hits: TP, FP, TP, FP, TP -> recall 1/3 @ P 1, 2/3 @ P 2/3, 1 @ P 3/5.
    ap = average_precision(np.array([1, 0, 1, 0, 1], bool), np.array([0.9, 0.8, 0.7, 0.6, 0.5]), 3)
    assert ap == pytest.approx(1 / 3 * 1.0 + 1 / 3 * 2 / 3 + 1 / 3 * 3 / 5)
    # The envelope: a later higher precision lifts earlier recall steps.
    ap = average_precision(np.array([0, 1, 1], bool), np.array([0.9, 0.8, 0.7]), 2)
    assert ap == pytest.approx(2 / 3)      # both recall steps at the envelope precision 2/3
    assert average_precision(np.array([], bool), np.array([]), 2) == 0.0
    assert math.isnan(average_precision(np.array([1], bool), np.array([0.5]), 0))
    # Unsorted input is ranked by score.
    assert average_precision(np.array([0, 1], bool), np.array([0.1, 0.9]), 1) == pytest.approx(1.0)


def test_perfect_and_missed_frames():
    ev = DetectionEval()
    truth = [[10, 10, 30, 50], [100, 100, 160, 140]]
    ev.add([[11, 10, 30, 50], [100, 101, 160, 140]], [0.9, 0.8], ["person", "car"], truth, ["person", "car"])
    ev.add([], [], [], [[10, 10, 30, 50]], ["person"])           # a frame where the person is missed
    s = ev.summary()
    assert s["frames"] == 2
    assert s["classes"]["car"]["AP50"] == pytest.approx(1.0)
    assert s["classes"]["person"]["AP50"] == pytest.approx(0.5)
    assert s["classes"]["person"]["recall"] == pytest.approx(0.5)
    assert s["classes"]["person"]["precision"] == pytest.approx(1.0)
    assert s["mAP50"] == pytest.approx(0.75)


def test_class_by_name_duplicates_and_low_iou_are_false_positives():
    ev = DetectionEval()
    truth = [[0, 0, 20, 40]]
    # wrong class, a duplicate of the same box, and a box at IoU < 0.5
    ev.add([[0, 0, 20, 40], [0, 0, 20, 40], [0, 0, 20, 40], [10, 0, 30, 40]], [0.9, 0.8, 0.7, 0.6],
           ["car", "person", "person", "person"], truth, ["person"])
    s = ev.summary()["classes"]
    assert s["person"]["AP50"] == pytest.approx(1.0)               # the best-ranked person is the TP
    assert s["person"]["precision"] == pytest.approx(1 / 3)
    assert s["car"]["truth"] == 0 and math.isnan(s["car"]["AP50"])
    assert ev.summary()["mAP50"] == pytest.approx(1.0)             # classes without truth are not averaged


def test_ignored_truth_neither_missed_nor_false_positive():
    ev = DetectionEval(min_height_px=12, min_visible=0.4)
    truth = [[0, 0, 20, 40], [50, 50, 54, 58], [100, 0, 120, 40]]   # ok, too small, too hidden
    ev.add([[50, 50, 54, 58], [100, 0, 120, 40]], [0.9, 0.8], ["person", "person"], truth,
           ["person"] * 3, [1.0, 1.0, 0.2])
    s = ev.summary()["classes"]["person"]
    assert s["truth"] == 1
    assert s["detections"] == 0 and s["recall"] == 0.0 and s["AP50"] == 0.0
    ev.add([[0, 0, 20, 40]], [0.5], ["person"], [[0, 0, 20, 40]], ["person"])
    assert ev.summary()["classes"]["person"]["AP50"] == pytest.approx(0.5)


def test_precision_recall_at_operating_threshold():
    ev = DetectionEval(conf_thresh=0.4)
    ev.add([[0, 0, 20, 40], [50, 0, 70, 40]], [0.9, 0.3], ["person", "person"],
           [[0, 0, 20, 40], [50, 0, 70, 40]], ["person", "person"])
    s = ev.summary()["classes"]["person"]
    assert s["AP50"] == pytest.approx(1.0)
    assert s["recall"] == pytest.approx(0.5) and s["precision"] == pytest.approx(1.0) and s["detections"] == 1
    assert "person" in format_table({"x": ev.summary()})


def test_height_histogram_bins_counted_truth_only():
    from aeroperception.services.detector.metrics import height_histogram

    h = height_histogram([5, 12, 23.9, 24, 100, 191.9, 192, 400])
    assert h == {"<12": 1, "12-24": 2, "24-48": 1, "48-96": 0, "96-192": 2, ">=192": 2}
    ev = DetectionEval()
    # 30 px counted; 8 px (too small) and a 50 px box 10 % visible are ignored: not in the histogram.
    ev.add(np.zeros((0, 4)), [], [], [[0, 0, 10, 30], [0, 0, 10, 8], [0, 0, 10, 50]], ["car"] * 3, [1.0, 1.0, 0.1])
    assert ev.summary()["truth_height_px"]["24-48"] == 1
    assert sum(ev.summary()["truth_height_px"].values()) == 1
    assert "truth px" in format_table({"x": ev.summary()})
