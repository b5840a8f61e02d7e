"""`aero eval detector`: mAP@0.5 and per-class precision/recall of a YOLOv8-format ONNX against
the simulator's truth boxes (services/detector/metrics.py holds the metric).

Offline (default): held-out renders from the simulator's own camera and truth-box projection
(tools/detector_data.py): the village with seeds training never used and the scenarios training
never saw (open_field, slope_forest), at drone poses from the ground up to 25 m.
Live (`--live`): a running stack's sensors/camera/left/image run through the model here, paired by
stamp with sim/truth/boxes; or (`--live --detections`) the detector service's own
perception/detections against sim/truth/boxes (its output is already thresholded at the
service's confidence, so its AP is computed over that truncated curve).
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from aeroperception.services.detector.metrics import DetectionEval, format_table

AP_CONF = 0.01        # keep low-score detections for the precision/recall curve


def default_model() -> str:
    return str(Path(__file__).resolve().parents[1] / "services/detector/models/aero_sim_det.onnx")


def _load(model_path: str, threads: int):
    from aeroperception.services.detector.yolo import ModelError, YoloModel

    from .common import CliError
    try:
        return YoloModel.load(model_path, threads=threads)
    except ModelError as e:
        raise CliError(str(e)) from None


def _add(ev: DetectionEval, model, image: np.ndarray, truth_boxes, truth_classes, truth_visible, nms: float) -> float:
    dets, ms = model.detect(image, conf_thresh=AP_CONF, nms_thresh=nms, channels="rgb")
    d = np.array(dets, float).reshape(-1, 6)
    ev.add(d[:, :4], d[:, 4], [model.names[int(k)] for k in d[:, 5]], truth_boxes, truth_classes, truth_visible)
    return sum(ms.values())


def evaluate_offline(model_path: str, n_per_set: int, threads: int = 2, sets: list[str] | None = None,
                     conf: float = 0.40, nms: float = 0.45, **eval_kw) -> dict[str, dict]:
    """Summaries per held-out set plus "all" (every frame pooled)."""
    from .detector_data import heldout_samples

    from .common import CliError

    model = _load(model_path, threads)
    try:
        sets_samples = heldout_samples(n_per_set, sets)
    except ValueError as e:
        raise CliError(str(e)) from None
    results, pooled, ms = {}, DetectionEval(conf_thresh=conf, **eval_kw), []
    for name, samples in sets_samples.items():
        ev = DetectionEval(conf_thresh=conf, **eval_kw)
        for s in samples:
            ms.append(_add(ev, model, s.image, s.boxes, s.classes, s.visible, nms))
            _add(pooled, model, s.image, s.boxes, s.classes, s.visible, nms)
        results[name] = ev.summary()
    results["all"] = pooled.summary()
    results["all"]["ms_median"] = float(np.median(ms)) if ms else float("nan")
    return results


def _report(results: dict[str, dict], json_out: str | None, header: str) -> int:
    print(header)
    print(format_table(results))
    if json_out:
        Path(json_out).write_text(json.dumps(results, indent=2, default=float))
        print(f"wrote {json_out}")
    return 0


def run_offline(model_path: str, n_per_set: int, json_out: str | None = None, threads: int = 2,
                sets: list[str] | None = None, **kw) -> int:
    res = evaluate_offline(model_path, n_per_set, threads, sets, **kw)
    a = res["all"]
    return _report(res, json_out, f"{model_path}: held-out sim renders, {a['frames']} frames, IoU {a['iou_thresh']}, "
                                  f"truth < {a['min_height_px']:g} px high or < {a['min_visible']:.0%} visible ignored; "
                                  f"P/R at conf {a['conf_thresh']}; {a.get('ms_median', float('nan')):.1f} ms/frame")


# ---------------------------------------------------------------- live

def _truth_arrays(msg):
    boxes = np.array([[d.center_x_px - d.size_x_px / 2, d.center_y_px - d.size_y_px / 2,
                       d.center_x_px + d.size_x_px / 2, d.center_y_px + d.size_y_px / 2] for d in msg.detections],
                     float).reshape(-1, 4)
    return boxes, [d.class_name for d in msg.detections], np.array([d.score for d in msg.detections], float)


def collect_live(session, duration_s: float, prefix: str, detections: bool, max_frames: int,
                 period_s: float = 0.2) -> list[tuple]:
    """Pairs (image or detections message, truth message) with equal stamps, at most one per
    period_s and max_frames in all, recorded for duration_s."""
    from aeroperception.schemas import Detection2DArray, Image, SchemaError, decode

    lock = threading.Lock()
    truth: dict[int, object] = {}
    other: dict[int, object] = {}
    pairs: list[tuple] = []
    last = [0.0]

    def match(stamp: int) -> None:
        if stamp in truth and stamp in other and len(pairs) < max_frames:
            pairs.append((other.pop(stamp), truth.pop(stamp)))
            last[0] = time.monotonic()

    def keeper(store: dict, cls, keep: int, throttle: bool):
        """Subscriber callback: decode, file by stamp (newest `keep`), pair when both are in."""
        def cb(sample) -> None:
            with lock:
                if throttle and (time.monotonic() - last[0] < period_s or len(pairs) >= max_frames):
                    return
            try:
                m = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            with lock:
                store[m.header.stamp_ns] = m
                match(m.header.stamp_ns)
                while len(store) > keep:
                    store.pop(next(iter(store)))
        return cb

    on_truth = keeper(truth, Detection2DArray, 200, throttle=False)
    on_other = keeper(other, Detection2DArray if detections else Image, 50, throttle=True)

    key = "perception/detections" if detections else "sensors/camera/left/image"
    subs = [session.declare_subscriber(prefix + "sim/truth/boxes", on_truth),
            session.declare_subscriber(prefix + key, on_other)]
    try:
        end = time.monotonic() + duration_s
        while time.monotonic() < end and len(pairs) < max_frames:
            time.sleep(0.05)
    finally:
        for s in subs:
            s.undeclare()
    with lock:
        return list(pairs)


def run_live(args) -> int:
    from .common import CliError, open_client

    prefix = f"{args.vehicle}/" if args.vehicle else ""
    session = open_client(args)
    try:
        what = "perception/detections" if args.detections else "sensors/camera/left/image"
        print(f"recording {what} and sim/truth/boxes for up to {args.duration:g} s ...", flush=True)
        pairs = collect_live(session, args.duration, prefix, args.detections, args.max_frames)
    finally:
        session.close()
    if not pairs:
        raise CliError(f"no {what} paired by stamp with sim/truth/boxes in {args.duration:g} s: is the "
                       f"simulator{' and the detector' if args.detections else ''} running (aero up)?")
    ev = DetectionEval(conf_thresh=args.conf)
    if args.detections:
        for det, tru in pairs:
            d_boxes, d_cls, d_scores = _truth_arrays(det)
            ev.add(d_boxes, d_scores, d_cls, *_truth_arrays(tru)[:2], _truth_arrays(tru)[2])
        source = "perception/detections (service-thresholded)"
    else:
        model = _load(args.model or default_model(), args.threads)
        for img, tru in pairs:
            b, c, v = _truth_arrays(tru)
            _add(ev, model, img.to_numpy(), b, c, v, args.nms)
        source = args.model or default_model()
    return _report({"live": ev.summary()}, args.json, f"{source}: live stream vs sim/truth/boxes, {len(pairs)} frames")
