"""Detection accuracy against truth boxes: AP@IoU per class, mAP, precision/recall.

The one home of the metric (`aero eval detector`, tools/training/train_detector.py, tests).

Matching (COCO/VOC style), per image and class: detections in descending score each take the
unmatched truth box of highest IoU >= iou_thresh (true positive); otherwise, if they overlap an
*ignored* truth box by >= iou_thresh they are dropped (neither TP nor FP); otherwise they are
false positives. Ignored truth boxes are those too small or too hidden to demand a detection
(KITTI's "don't care"): height below min_height_px or visible fraction (sim/truth/boxes score)
below min_visible; they are not counted as misses either.

AP is the area under the precision envelope over all recall points (VOC 2010+ / all-point
interpolation). mAP averages the classes that have truth boxes. Precision/recall are reported at
the operating threshold `conf_thresh` (the detector service's confidence, 0.40 by default).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DEFAULT_MIN_HEIGHT_PX = 12.0
DEFAULT_MIN_VISIBLE = 0.4
# Pixel-height bins of the counted truth boxes: the apparent size decides detectability, and it is
# what a live flight and the held-out renders can be compared by (a 1.7 m person at the sim
# camera's 320 px focal length: 24 px ~ 23 m, 48 px ~ 11 m, 96 px ~ 6 m).
HEIGHT_BINS_PX = (12.0, 24.0, 48.0, 96.0, 192.0)


def height_histogram(heights, bins=HEIGHT_BINS_PX) -> dict[str, int]:
    """Counts of box heights per bin ("12-24", ..., ">=192"); heights below the first edge go to "<12"."""
    h = np.asarray(heights, float).reshape(-1)
    edges = list(bins)
    out = {f"<{edges[0]:g}": int((h < edges[0]).sum())}
    for lo, hi in zip(edges[:-1], edges[1:]):
        out[f"{lo:g}-{hi:g}"] = int(((h >= lo) & (h < hi)).sum())
    out[f">={edges[-1]:g}"] = int((h >= edges[-1]).sum())
    return out


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Na, Nb) IoU of xyxy boxes."""
    a = np.asarray(a, float).reshape(-1, 4)
    b = np.asarray(b, float).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(2)
    area_a = np.clip(a[:, 2:] - a[:, :2], 0, None).prod(1)
    area_b = np.clip(b[:, 2:] - b[:, :2], 0, None).prod(1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def average_precision(tp: np.ndarray, scores: np.ndarray, n_truth: int) -> float:
    """All-point interpolated AP of detections (tp flags, scores) against n_truth boxes."""
    if n_truth == 0:
        return float("nan")
    if len(tp) == 0:
        return 0.0
    order = np.argsort(-np.asarray(scores, float), kind="stable")
    hits = np.asarray(tp, float)[order]
    ctp, cfp = np.cumsum(hits), np.cumsum(1.0 - hits)
    recall = ctp / n_truth
    precision = ctp / np.maximum(ctp + cfp, 1e-12)
    r = np.concatenate([[0.0], recall, [recall[-1]]])
    p = np.concatenate([[1.0], precision, [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]
    steps = np.flatnonzero(r[1:] != r[:-1])
    return float(np.sum((r[steps + 1] - r[steps]) * p[steps + 1]))


@dataclass
class _ClassAcc:
    scores: list[float] = field(default_factory=list)
    tp: list[bool] = field(default_factory=list)
    n_truth: int = 0


@dataclass
class DetectionEval:
    """Accumulate frames with `add`, read the figures with `summary`."""
    iou_thresh: float = 0.5
    min_height_px: float = DEFAULT_MIN_HEIGHT_PX
    min_visible: float = DEFAULT_MIN_VISIBLE
    conf_thresh: float = 0.40
    frames: int = 0
    acc: dict[str, _ClassAcc] = field(default_factory=dict)
    heights: list[float] = field(default_factory=list)   # pixel height of every counted truth box

    def _cls(self, name: str) -> _ClassAcc:
        return self.acc.setdefault(name, _ClassAcc())

    def add(self, det_boxes, det_scores, det_classes, truth_boxes, truth_classes, truth_visible=None) -> None:
        """One frame. Boxes xyxy in the same pixels; classes by name (a model's ids need not be
        the simulator's COCO ids); truth_visible None means fully visible."""
        self.frames += 1
        det_boxes = np.asarray(det_boxes, float).reshape(-1, 4)
        det_scores = np.asarray(det_scores, float).reshape(-1)
        truth_boxes = np.asarray(truth_boxes, float).reshape(-1, 4)
        vis = np.ones(len(truth_boxes)) if truth_visible is None else np.asarray(truth_visible, float).reshape(-1)
        ignored = ((truth_boxes[:, 3] - truth_boxes[:, 1]) < self.min_height_px) | (vis < self.min_visible)
        det_classes, truth_classes = list(det_classes), list(truth_classes)
        self.heights.extend((truth_boxes[~ignored, 3] - truth_boxes[~ignored, 1]).tolist())
        for name in set(det_classes) | set(truth_classes):
            acc = self._cls(name)
            ti = [i for i, c in enumerate(truth_classes) if c == name]
            di = [i for i, c in enumerate(det_classes) if c == name]
            gt, ign = truth_boxes[ti], ignored[ti]
            acc.n_truth += int((~ign).sum())
            di = sorted(di, key=lambda i: -det_scores[i])
            ious = iou_matrix(det_boxes[di], gt)
            taken = np.zeros(len(gt), bool)
            for row, i in enumerate(di):
                cand = np.where(~ign & ~taken, ious[row], -1.0) if len(gt) else np.empty(0)
                if len(cand) and cand.max() >= self.iou_thresh:
                    taken[int(cand.argmax())] = True
                    acc.tp.append(True)
                elif len(gt) and np.any(ign & (ious[row] >= self.iou_thresh)):
                    continue            # a detection of an ignored box: not counted
                else:
                    acc.tp.append(False)
                acc.scores.append(float(det_scores[i]))

    def summary(self) -> dict:
        """{"mAP50": float, "frames": int, "classes": {name: {AP50, precision, recall, truth,
        detections}}, "truth_height_px": histogram} with precision/recall at conf_thresh."""
        classes = {}
        for name in sorted(self.acc):
            a = self.acc[name]
            tp, sc = np.array(a.tp, bool), np.array(a.scores, float)
            op = sc >= self.conf_thresh
            ntp = int(tp[op].sum())
            classes[name] = {
                "AP50": average_precision(tp, sc, a.n_truth),
                "precision": ntp / int(op.sum()) if op.any() else float("nan"),
                "recall": ntp / a.n_truth if a.n_truth else float("nan"),
                "truth": a.n_truth, "detections": int(op.sum()),
            }
        aps = [c["AP50"] for c in classes.values() if c["truth"] > 0]
        return {"mAP50": float(np.mean(aps)) if aps else float("nan"), "frames": self.frames,
                "iou_thresh": self.iou_thresh, "min_height_px": self.min_height_px,
                "min_visible": self.min_visible, "conf_thresh": self.conf_thresh, "classes": classes,
                "truth_height_px": height_histogram(self.heights)}


def format_table(results: dict[str, dict]) -> str:
    """A table of several summaries (name -> summary): one row per set and class."""
    lines = [f"{'set':<16} {'class':<9} {'AP50':>6} {'P':>6} {'R':>6} {'truth':>6} {'dets':>6}"]
    for name, s in results.items():
        for cname, c in s["classes"].items():
            if c["truth"] == 0 and c["detections"] == 0:
                continue
            lines.append(f"{name:<16} {cname:<9} {c['AP50']:>6.3f} {c['precision']:>6.3f} {c['recall']:>6.3f} "
                         f"{c['truth']:>6d} {c['detections']:>6d}")
        lines.append(f"{name:<16} {'mAP@0.5':<9} {s['mAP50']:>6.3f}   ({s['frames']} frames)")
        if "truth_height_px" in s:
            lines.append(f"{name:<16} {'truth px':<9} " + "  ".join(f"{k}:{v}" for k, v in s["truth_height_px"].items()))
    return "\n".join(lines)
