"""The detector as a real process under `aero up`, fed camera frames over Zenoh by the test:
detections come back at the painted pixels with the model's class names and the image's stamp,
at no more than the configured rate; the model is hot-swapped through the live parameter
(good -> swapped; missing file / non-YOLO ONNX / garbage bytes -> `aero param set` is refused with
the reason, the old model keeps running and `aero param list` still names it; good again -> OK);
started without a model it runs, reports ERROR with the reason, and takes one through the parameter.

The models are hand-built ONNX graphs (tests/detector_graphs.py) that find solid colour blocks,
so every box the service publishes can be checked against where the block really is.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from aerotest import wait_for_message
from detector_graphs import box_finder_model, classifier_model, paint_blocks

from aeroperception.schemas import (
    DiagnosticStatus, Detection2DArray, Header, Image, ParamSet, ParamSetReply, decode, encode,
)
from aeroperception.services.runtime.node import call as rpc_call, encoding_for

pytestmark = pytest.mark.timeout(180)

HW = (480, 640)
BLOCKS = {0: (40, 60, 200, 180), 1: (500, 300, 640, 480), 2: (301, 201, 377, 263)}
FEED_HZ = 30.0


class _Camera:
    """Publishes the painted frame as rgb8 at FEED_HZ (stamps = wall ns) until stopped."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.stop = threading.Event()
        self.frame = paint_blocks(HW, BLOCKS, "rgb")
        self.stamps: set[int] = set()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        pub = self.session.declare_publisher("sensors/camera/left/image", encoding=encoding_for(Image))
        for _ in range(int(FEED_HZ * 170)):                      # bounded: the module's timeout
            if self.stop.is_set():
                break
            stamp = time.time_ns()
            self.stamps.add(stamp)
            pub.put(encode(Image.from_numpy(self.frame, "rgb8", Header(stamp_ns=stamp, frame_id="camera_left_optical"))))
            time.sleep(1.0 / FEED_HZ)
        pub.undeclare()


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    (d / "garbage.onnx").write_bytes(np.random.default_rng(3).bytes(20000))
    return {"a": box_finder_model(d / "a.onnx", names=["red", "green", "blue"]),
            "b": box_finder_model(d / "b.onnx", layout="channels_last", names=["r", "g", "b"]),
            "classifier": classifier_model(d / "classifier.onnx"),
            "garbage": d / "garbage.onnx", "missing": d / "missing.onnx"}


@pytest.fixture(scope="module")
def det(stack_module, models):
    st = stack_module(["detector"], extra_args=["--arg", f"detector:--param=model_path={models['a']}"])
    cam = _Camera(st.session)
    yield st
    cam.stop.set()
    cam.thread.join(5)


def _set(st, name, value):
    reply = rpc_call(st.session, "config/detector/@set", ParamSet(name=name, value=value), ParamSetReply, timeout_s=5)
    assert reply.success, reply.message


def _record(st, key, cls, seconds):
    got, lock = [], threading.Lock()

    def on_sample(s):
        msg = decode(s.payload.to_bytes(), cls)
        with lock:
            got.append((time.monotonic(), msg))

    sub = st.session.declare_subscriber(key, on_sample)
    time.sleep(seconds)
    sub.undeclare()
    with lock:
        return list(got)


def _names(msg: Detection2DArray) -> list[str]:
    return sorted(d.class_name for d in msg.detections)


def test_detections_are_at_the_painted_pixels_with_names_and_stamp(det):
    msg = wait_for_message(det.session, "perception/detections", Detection2DArray,
                           lambda m: len(m.detections) == 3, timeout_s=20)
    assert (msg.image_width, msg.image_height) == (640, 480) and msg.header.frame_id == "camera_left_optical"
    assert msg.header.stamp_ns > 0
    assert _names(msg) == ["blue", "green", "red"]
    for d in msg.detections:
        x1, y1, x2, y2 = BLOCKS[d.class_id]
        got = (d.center_x_px - d.size_x_px / 2, d.center_y_px - d.size_y_px / 2,
               d.center_x_px + d.size_x_px / 2, d.center_y_px + d.size_y_px / 2)
        assert np.abs(np.subtract(got, (x1, y1, x2, y2))).max() <= 1.0, (d, BLOCKS[d.class_id])
        assert d.score == pytest.approx(0.9, abs=1e-6)


def test_output_rate_is_at_most_the_configured_rate(det):
    wait_for_message(det.session, "perception/detections", Detection2DArray, timeout_s=20)
    for rate in (10.0, 4.0):
        _set(det, "inference_frequency_hz", rate)
        time.sleep(1.0)                                         # let the old rate's frames drain
        got = _record(det, "perception/detections", Detection2DArray, 4.0)
        hz = (len(got) - 1) / (got[-1][0] - got[0][0])
        assert 0.7 * rate <= hz <= 1.1 * rate, f"{hz:.1f} Hz with inference_frequency_hz={rate} (camera {FEED_HZ} Hz)"
    health = wait_for_message(det.session, "perception/detector_health", DiagnosticStatus, timeout_s=5)
    assert int(health.values["frames_skipped_rate"]) > 0 and health.name == "detector"
    _set(det, "inference_frequency_hz", 10.0)


def _health(st, pred, what, timeout_s=15.0) -> DiagnosticStatus:
    try:
        return wait_for_message(st.session, "perception/detector_health", DiagnosticStatus, pred, timeout_s=timeout_s)
    except AssertionError as e:
        raise AssertionError(f"{what}: {e}\n{st.service_log('detector')[-3000:]}") from None


def test_hot_swap_through_the_live_parameter(det, models):
    _set(det, "model_path", str(models["b"]))
    wait_for_message(det.session, "perception/detections", Detection2DArray, lambda m: _names(m) == ["b", "g", "r"],
                     timeout_s=15)
    _health(det, lambda h: h.level == DiagnosticStatus.OK and h.values.get("model") == str(models["b"]), "b is OK")
    for bad, reason in [("missing", "model file not found"), ("classifier", "output shape [1, 1000] is not a YOLOv8"),
                        ("garbage", "not a loadable ONNX model")]:
        # The set is refused with the reason; the parameter keeps naming the model that runs.
        res = det.aero("param", "set", "detector", "model_path", str(models[bad]))
        assert res.returncode == 1 and reason in res.stderr and "still running b.onnx" in res.stderr, res.stderr
        listed = det.aero("param", "get", "detector", "model_path")
        assert listed.returncode == 0 and listed.stdout.strip() == str(models["b"]), listed.stdout
        h = _health(det, lambda h: reason in h.values.get("model_refused", ""), f"{bad} refused")
        assert h.level == DiagnosticStatus.OK and h.values["model"] == str(models["b"])
        # The old model keeps detecting: a frame stamped after the refusal, with b's names.
        after = time.time_ns()
        m = wait_for_message(det.session, "perception/detections", Detection2DArray,
                             lambda m: m.header.stamp_ns > after, timeout_s=10)
        assert _names(m) == ["b", "g", "r"]
    _set(det, "model_path", str(models["a"]))
    _health(det, lambda h: h.level == DiagnosticStatus.OK and h.values.get("model") == str(models["a"])
            and "model_refused" not in h.values, "a again OK")
    wait_for_message(det.session, "perception/detections", Detection2DArray,
                     lambda m: _names(m) == ["blue", "green", "red"], timeout_s=10)


def test_starts_without_a_model_reports_error_then_takes_one(stack, models, tmp_path):
    st = stack(["detector"], extra_args=["--arg", f"detector:--param=model_path={tmp_path / 'none.onnx'}"])
    h = _health(st, lambda h: h.level == DiagnosticStatus.ERROR, "no model at start")
    assert h.message.startswith("no model: model file not found") and "none.onnx" in h.message
    _set(st, "model_path", str(models["a"]))
    h = _health(st, lambda h: h.level != DiagnosticStatus.ERROR, "a model after start")
    assert h.message == "no camera image yet" and h.values["model"] == str(models["a"])
