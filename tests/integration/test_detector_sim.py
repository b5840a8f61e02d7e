"""The detector inside the onboard stack on the village scenario (`aero up --scenario village`:
sim rendering camera + LiDAR, fmu, planner, mission, safety, diagnostics, lidar, vio, detector):
detections arrive at the configured rate -- or at the camera's rate when the loaded 2-core
machine renders fewer frames than that -- each stamped with a camera frame's stamp and sized
like it. The bundled model runs when it is in the package; until then a hand-built graph does.
"""
from __future__ import annotations

import threading
import time

import pytest

from aerotest import free_udp_port, wait_for_message
from detector_graphs import box_finder_model

from aeroperception.schemas import DiagnosticStatus, Detection2DArray, Image, SchemaError, decode
from aeroperception.services.detector import contract
from aeroperception.services.detector.logic import resolve_model_path

pytestmark = pytest.mark.timeout(240)

RATE_HZ = 10.0
WINDOW_S = 8.0
ONBOARD = ["sim", "fmu", "planner", "mission", "diagnostics", "safety", "lidar", "vio", "detector"]


@pytest.fixture(scope="module")
def village(stack_module, tmp_path_factory):
    bundled = resolve_model_path(contract.BUNDLED_MODEL)
    model = bundled if bundled.is_file() else box_finder_model(tmp_path_factory.mktemp("m") / "finder.onnx")
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack_module(ONBOARD, extra_args=[
        "--scenario", "village", "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
        "--arg", f"detector:--param=model_path={model}",
        "--arg", f"detector:--param=inference_frequency_hz={RATE_HZ}"], timeout_s=60)
    try:
        wait_for_message(st.session, "perception/detections", Detection2DArray, timeout_s=60)
    except AssertionError as e:
        raise AssertionError(f"{e}\n{st.describe()}") from None
    time.sleep(2.0)                                          # let render and inference rates settle
    return st, model


def test_detections_arrive_at_the_configured_rate_with_the_stack_running(village):
    st, model = village
    recv: dict[str, list] = {"sensors/camera/left/image": [], "perception/detections": []}
    lock = threading.Lock()

    def on(key, cls):
        def cb(sample):
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            with lock:
                recv[key].append((time.monotonic(), msg.header.stamp_ns, msg))
        return cb

    subs = [st.session.declare_subscriber(k, on(k, c)) for k, c in
            (("sensors/camera/left/image", Image), ("perception/detections", Detection2DArray))]
    time.sleep(WINDOW_S)
    for s in subs:
        s.undeclare()
    with lock:
        images, dets = list(recv["sensors/camera/left/image"]), list(recv["perception/detections"])

    def hz(rows):
        return (len(rows) - 1) / (rows[-1][0] - rows[0][0]) if len(rows) > 1 else 0.0

    camera_hz, det_hz = hz(images), hz(dets)
    health = wait_for_message(st.session, "perception/detector_health", DiagnosticStatus, timeout_s=5)
    why = (f"detections {det_hz:.1f} Hz, camera {camera_hz:.1f} Hz, configured {RATE_HZ:g} Hz, model {model}; "
           f"health {health.level_name} {health.message} {dict(health.values)}")
    print(why)
    assert det_hz <= RATE_HZ * 1.1, why
    assert det_hz >= 0.75 * min(RATE_HZ, camera_hz), why
    assert camera_hz >= 1.0, why                             # the stack is really rendering
    image_stamps = {s for _, s, _ in images}
    stamped = [s for _, s, _ in dets if s in image_stamps]
    assert len(stamped) >= 0.9 * len(dets) - 2, "every detection carries its frame's stamp"
    w, h = images[0][2].width, images[0][2].height
    assert all((m.image_width, m.image_height) == (w, h) for _, _, m in dets)
    assert health.level != DiagnosticStatus.ERROR, why
