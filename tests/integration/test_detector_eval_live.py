"""`aero eval detector --live` on a running village stack (sim + detector): the camera stream run
through the bundled model here and the detector service's own perception/detections, both
against sim/truth/boxes, land within a few points of each other and find the street's people and cars.
The flight test (`--until-landed` over examples/missions/village_tour.json on the whole onboard
stack, ~4 min) holds the live mAP within 0.1 of the held-out village renders measured in the same test.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aerotest import free_udp_port, wait_for_message

from aeroperception.schemas import Detection2DArray, PerceptionHealth
from aeroperception.services.detector import contract
from aeroperception.services.detector.logic import resolve_model_path

# extended: test_detector_sim covers the live service on the stack; this compares the two eval modes.
pytestmark = [pytest.mark.slow, pytest.mark.extended, pytest.mark.timeout(240)]


def _eval(stack, tmp_path, *extra: str) -> dict:
    out = tmp_path / f"eval{len(extra)}.json"
    argv = [sys.executable, "-m", "aeroperception.tools.cli", "eval", "detector", "--live", "--connect", stack.endpoint,
            "--duration", "20", "--max-frames", "12", "--threads", "1", "--json", str(out), *extra]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=90, env={**os.environ, "AERO_VEHICLE": ""})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    print(proc.stdout)
    return json.loads(out.read_text())["live"]


def test_live_eval_of_the_camera_stream_and_of_the_service(stack, tmp_path):
    model = resolve_model_path(contract.BUNDLED_MODEL)
    assert model.is_file(), "the bundled model is part of the package"
    st = stack(["sim", "detector"], extra_args=["--scenario", "village"], timeout_s=60)
    wait_for_message(st.session, "perception/detections", Detection2DArray, timeout_s=60)
    time.sleep(1.0)
    here = _eval(st, tmp_path)
    service = _eval(st, tmp_path, "--detections")
    assert here["frames"] >= 5 and service["frames"] >= 5
    # The vehicle stands at the start looking down the street: people and cars are in view, most
    # of them far (the truck ~70 m away); one static view, so no comparison with held-out sets.
    for res in (here, service):
        assert res["classes"]["person"]["truth"] > 0 and res["classes"]["car"]["truth"] > 0
        assert res["classes"]["person"]["recall"] >= 0.5 and res["classes"]["car"]["recall"] >= 0.3, res
    # The service runs the same model at its 0.40 threshold: both evaluations agree within a few points.
    assert abs(here["mAP50"] - service["mAP50"]) <= 0.1, (here, service)
    for cls in ("person", "car"):
        assert abs(here["classes"][cls]["recall"] - service["classes"][cls]["recall"]) <= 0.1, (here, service)


# ---------------------------------------------------------------- one flight, both modes, vs held-out

TOUR = Path(__file__).resolve().parents[2] / "examples" / "missions" / "village_tour.json"
ONBOARD = ["sim", "fmu", "planner", "mission", "diagnostics", "safety", "lidar", "vio", "perception", "detector"]
# Half real time (every service follows sim/clock): two evaluations beside the whole stack on a
# shared 2-core machine starved fmu for 0.6 s at real time once (mission HOLDING on the outage).
SPEED = 0.5


def _popen(stack, *argv: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "aeroperception.tools.cli", *argv, "--connect", stack.endpoint],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL,
                            env={**os.environ, "AERO_VEHICLE": ""})


def _finish(p: subprocess.Popen, timeout_s: float) -> str:
    try:
        out, _ = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate()
    return out


@pytest.mark.timeout(1200)
def test_live_eval_over_a_village_flight_matches_the_held_out_renders(stack, tmp_path):
    """`aero up --scenario village` (whole onboard stack), `aero mission fly village_tour.json`, and
    `aero eval detector --live --until-landed` in both modes over that flight: the camera stream
    through the bundled model scores within 0.1 mAP of the held-out village renders measured here."""
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack(ONBOARD, extra_args=[
        "--scenario", "village", "--speed", str(SPEED), "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}"], timeout_s=60)
    wait_for_message(st.session, "perception/detections", Detection2DArray, timeout_s=60)
    wait_for_message(st.session, "perception/health", PerceptionHealth, lambda m: m.overall_healthy, 90)
    out = {m: tmp_path / f"{m}.json" for m in ("camera", "service", "heldout")}
    evals = [_popen(st, "eval", "detector", "--live", "--until-landed", "--duration", "700", "--threads", "1",
                    "--json", str(out["camera"])),
             _popen(st, "eval", "detector", "--live", "--detections", "--until-landed", "--duration", "700",
                    "--json", str(out["service"]))]
    try:
        time.sleep(2.0)
        fly = _popen(st, "mission", "fly", str(TOUR), "--quiet", "--timeout", "600")
        fly_out = _finish(fly, 620)
        assert fly.returncode == 0, f"fly exit {fly.returncode}\n{fly_out}\n{st.describe()}"
        logs = [_finish(p, 60) for p in evals]
    finally:
        for p in evals:
            if p.poll() is None:
                p.kill()
    print("\n".join(logs))
    assert all(p.returncode == 0 for p in evals), logs
    held = subprocess.run([sys.executable, "-m", "aeroperception.tools.cli", "eval", "detector", "--set", "village@1001",
                           "--set", "village@1002", "--threads", "1", "--json", str(out["heldout"])],
                          capture_output=True, text=True, timeout=400)
    print(held.stdout)
    assert held.returncode == 0, held.stdout + held.stderr
    cam, svc = (json.loads(out[m].read_text())["live"] for m in ("camera", "service"))
    ref = json.loads(out["heldout"].read_text())["all"]
    assert cam["frames"] >= 30 and svc["frames"] >= 30, (cam["frames"], svc["frames"])
    for cls in ("person", "car", "truck", "bicycle"):
        assert cam["classes"][cls]["truth"] > 0, f"the tour never saw a {cls}"
    assert abs(cam["mAP50"] - ref["mAP50"]) <= 0.1, (cam["mAP50"], ref["mAP50"])
    # The service keeps up and never queues: a frame that arrives while one is inferred replaces the
    # waiting one (newest wins, counted); on 2 shared cores that happens now and then (7 of 1015 with
    # the 480x640 model), never as a backlog. Every frame is accounted for.
    d = svc["detector"]
    assert d["frames_received"] > 0 and d["frames_dropped_busy"] <= 0.03 * d["frames_received"], d
    assert d["frames_processed"] >= d["frames_received"] - d["frames_skipped_rate"] - d["frames_dropped_busy"] - 2, d
