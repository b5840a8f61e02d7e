"""`aero eval detector`: mAP@0.5 and per-class precision/recall of a YOLOv8-format ONNX against
the simulator's truth boxes (services/detector/metrics.py holds the metric).

Offline (default): held-out renders from the simulator's own camera and truth-box projection
(tools/training/detector_data.py): the village with seeds training never used and the scenarios training
never saw (open_field, slope_forest), at drone poses from the ground up to 25 m.
Live (`--live`): a running stack's sensors/camera/left/image run through the model here, paired by
stamp with sim/truth/boxes; or (`--live --detections`) the detector service's own
perception/detections against sim/truth/boxes (its output is already thresholded at the
service's confidence, so its AP is computed over that truncated curve). `--until-landed` evaluates
one flight (e.g. `aero mission fly examples/missions/village_tour.json`) as it flies: every paired
frame by default, in a short newest-wins queue so nothing piles up in memory; the report adds the
camera / detections rates beside the detector's configured rate, the detector service's own
received / processed / skipped counters over the window, and the pixel-height histogram of the
truth boxes counted (what makes a flight comparable with the held-out renders).
"""
from __future__ import annotations

import json
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aeroperception.services.detector.metrics import DetectionEval, format_table

AP_CONF = 0.01        # keep low-score detections for the precision/recall curve


def default_model() -> str:
    return str(Path(__file__).resolve().parents[2] / "services/detector/models/aero_sim_det.onnx")


def _load(model_path: str, threads: int):
    from aeroperception.services.detector.yolo import ModelError, YoloModel

    from aeroperception.tools.common import CliError
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
    from aeroperception.tools.training.detector_data import heldout_samples

    from aeroperception.tools.common import CliError

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


class StampPairer:
    """Pairs two streams by equal header stamps (the renderer publishes each left image and its
    truth boxes with one stamp). Each side keeps its newest `keep` unmatched messages; `add`
    returns (a, b) when the other side already holds that stamp."""

    def __init__(self, keep: int = 50):
        self.keep = keep
        self.sides: tuple[dict, dict] = ({}, {})

    def add(self, side: int, stamp: int, msg) -> tuple | None:
        mine, other = self.sides[side], self.sides[1 - side]
        if stamp in other:
            o = other.pop(stamp)
            return (msg, o) if side == 0 else (o, msg)
        mine[stamp] = msg
        while len(mine) > self.keep:
            mine.pop(next(iter(mine)))
        return None


@dataclass
class LiveWindow:
    """What the live window saw: message counts (for rates) and the detector's own counters."""
    seconds: float = 0.0
    camera: int = 0                    # sensors/camera/left/image messages
    truth: int = 0                     # sim/truth/boxes messages
    detections: int = 0                # perception/detections messages
    pairs: int = 0                     # pairs evaluated
    dropped: int = 0                   # pairs not evaluated (this tool fell behind; newest wins)
    health: list = field(default_factory=list)   # perception/detector_health values, first and last

    def rates(self) -> dict[str, float]:
        s = max(self.seconds, 1e-9)
        return {"camera_hz": self.camera / s, "truth_hz": self.truth / s, "detections_hz": self.detections / s,
                "evaluated_hz": self.pairs / s}

    def detector_counts(self) -> dict[str, int]:
        """Counter deltas of the detector service over the window (empty without its health)."""
        if len(self.health) < 2:
            return {}
        a, b = self.health[0], self.health[-1]
        return {k: int(b[k]) - int(a[k]) for k in ("frames_received", "frames_processed", "frames_skipped_rate",
                                                     "frames_dropped_busy") if k in a and k in b}


def collect_live(session, duration_s: float, prefix: str, detections: bool, max_frames: int,
                 on_pair, period_s: float = 0.0, until_landed: bool = False, max_pending: int = 4) -> LiveWindow:
    """Record sensors/camera/left/image (or perception/detections) and sim/truth/boxes for
    duration_s, or (until_landed) until the vehicle has flown and is down and disarmed again,
    calling on_pair(other, truth) in this thread for each stamp-paired frame (at most one per
    period_s, max_frames in all). Pairs wait in a short newest-wins queue so a slow evaluation
    never holds frames in memory; those it drops are counted."""
    from aeroperception.schemas import (Detection2DArray, DiagnosticStatus, Image, SchemaError,
                                        decode)

    lock = threading.Lock()
    from aeroperception.tools.common import FlightWatch

    pairer, pending, win, watch = StampPairer(), deque(), LiveWindow(), FlightWatch()
    last = [-1e9]

    def pair_in(side: int, cls, counter: str):
        def cb(sample) -> None:
            with lock:
                setattr(win, counter, getattr(win, counter) + 1)
            try:
                m = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            with lock:
                p = pairer.add(side, m.header.stamp_ns, m)
                if p is None or time.monotonic() - last[0] < period_s:
                    return
                last[0] = time.monotonic()
                pending.append(p)
                while len(pending) > max_pending:
                    pending.popleft()
                    win.dropped += 1
        return cb

    def on_health(sample) -> None:
        try:
            m = decode(sample.payload.to_bytes(), DiagnosticStatus)
        except SchemaError:
            return
        with lock:
            win.health[min(len(win.health), 1):] = [dict(m.values)]     # [first, latest]

    def on_count(sample) -> None:
        with lock:
            win.camera += 1

    key = "perception/detections" if detections else "sensors/camera/left/image"
    subs = [session.declare_subscriber(prefix + "sim/truth/boxes", pair_in(1, Detection2DArray, "truth")),
            session.declare_subscriber(prefix + key, pair_in(0, Detection2DArray if detections else Image,
                                                              "detections" if detections else "camera")),
            session.declare_subscriber(prefix + "perception/detector_health", on_health)]
    if detections:
        subs.append(session.declare_subscriber(prefix + "sensors/camera/left/image", on_count))
    if until_landed:
        subs.append(session.declare_subscriber(prefix + "sim/truth/state", watch.on_sample))
    t0 = time.monotonic()
    try:
        end = t0 + duration_s
        while time.monotonic() < end and win.pairs < max_frames and not watch.down.is_set():
            with lock:
                p = pending.popleft() if pending else None
            if p is None:
                time.sleep(0.02)
                continue
            on_pair(*p)
            win.pairs += 1
    finally:
        for s in subs:
            s.undeclare()
    win.seconds = time.monotonic() - t0
    return win


def _configured_rate(session, args) -> float | None:
    """The detector service's inference_frequency_hz, or None when it does not answer."""
    from aeroperception.schemas import ParamList

    from aeroperception.tools.cli.topic import call_or_fail
    from aeroperception.tools.common import CliError, full_key
    try:
        plist = call_or_fail(session, full_key(args, "config/detector/@params"), None, ParamList, timeout_s=2.0)
    except CliError:
        return None
    return next((float(p.value) for p in plist.params if p.name == "inference_frequency_hz"), None)


def run_live(args) -> int:
    from aeroperception.tools.common import CliError, open_client

    prefix = f"{args.vehicle}/" if args.vehicle else ""
    until = getattr(args, "until_landed", False)
    max_frames = args.max_frames if args.max_frames is not None else (100_000 if until else 60)
    ev = DetectionEval(conf_thresh=args.conf)
    if args.detections:
        source = "perception/detections (service-thresholded)"

        def on_pair(det, tru) -> None:
            d_boxes, d_cls, d_scores = _truth_arrays(det)
            ev.add(d_boxes, d_scores, d_cls, *_truth_arrays(tru))
    else:
        model = _load(args.model or default_model(), args.threads)
        source = args.model or default_model()

        def on_pair(img, tru) -> None:
            _add(ev, model, img.to_numpy(), *_truth_arrays(tru), args.nms)
    what = "perception/detections" if args.detections else "sensors/camera/left/image"
    session = open_client(args)
    try:
        configured = _configured_rate(session, args)
        print(f"recording {what} and sim/truth/boxes for {args.duration:g} s"
              + (" at most, until the vehicle has flown and landed" if until else "") + " ...", flush=True)
        win = collect_live(session, args.duration, prefix, args.detections, max_frames, on_pair,
                           args.period, until)
    finally:
        session.close()
    if not win.pairs:
        raise CliError(f"no {what} paired by stamp with sim/truth/boxes in {win.seconds:.0f} s: is the "
                       f"simulator{' and the detector' if args.detections else ''} running (aero up)?")
    res = ev.summary()
    res.update(win.rates(), window_s=win.seconds, pairs_dropped=win.dropped, configured_hz=configured,
               detector=win.detector_counts())
    r = win.rates()
    cfg = f"{configured:g} Hz" if configured is not None else "unknown (no detector service)"
    det = win.detector_counts()
    header = (f"{source}: live stream vs sim/truth/boxes, {win.pairs} frames in {win.seconds:.0f} s "
              f"({win.dropped} not evaluated); camera {r['camera_hz']:.2f} Hz, "
              + (f"detections {r['detections_hz']:.2f} Hz, " if args.detections else "")
              + f"configured {cfg}"
              + (f"; detector received {det.get('frames_received')} processed {det.get('frames_processed')} "
                 f"rate-skipped {det.get('frames_skipped_rate')} busy-dropped {det.get('frames_dropped_busy')}"
                 if det else ""))
    return _report({"live": res}, args.json, header)
