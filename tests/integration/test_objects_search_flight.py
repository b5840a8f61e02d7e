"""The objects service's goals on the village search flight (opt-in, ~3.5-5 min): the onboard stack
with the camera, `aero mission fly examples/missions/village_search.json` and
`aero eval objects --live --until-landed` over that flight; every person, car, truck and bicycle
target is found exactly once, no false track lives > 2 s, position error at 5-30 m has median
< 0.5 m and p95 < 1.5 m, and the service's CPU per detection frame stays < 5 ms (p99).
The service's inputs are recorded (`aero record`, the stereo pair included) into the test's tmp dir:
a failure seen only live prints the `aero eval objects --replay` command that plays it again.
test_objects_stack.py holds a short pass on the default run to the same per-object rules.
"""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from aerotest import aero_argv, clean_env, free_udp_port, interrupt, wait_for_message, wait_until
from test_detector_eval_live import _finish, _popen

from aeroperception.schemas import Detection2DArray
from aeroperception.tools.eval.objects import REPLAY_INPUTS, unmet_goals

pytestmark = [pytest.mark.slow, pytest.mark.extended, pytest.mark.timeout(2400)]

SEARCH = Path(__file__).resolve().parents[2] / "examples" / "missions" / "village_search.json"
SERVICES = ["sim", "fmu", "planner", "mission", "diagnostics", "safety", "detector", "objects"]
# Half real time (every service follows sim/clock): on 2 shared cores the camera renders a few
# frames a wall second; at half speed the detector sees twice as many per metre flown.
SPEED = 0.5
MAX_RESUMES = 5


def _fly_resuming(st, timeout_s: float) -> tuple[int, str, int]:
    """Fly the search; a hold the stack takes under load mid-mission (fmu outage, a service's
    diagnostics late) is resumed with START, at most MAX_RESUMES times: the subject here is the
    objects, the holds are the safety tests'. (exit code, output, resumes)."""
    fly = _popen(st, "mission", "fly", str(SEARCH), "--quiet", "--timeout", str(int(timeout_s)))
    resumes, flying, deadline = 0, False, time.monotonic() + timeout_s + 30
    try:
        while fly.poll() is None and time.monotonic() < deadline:
            state = st.mission_state(timeout_s=2.0)
            flying = flying or state == "EXECUTING"
            if flying and state == "HOLDING" and resumes < MAX_RESUMES:
                resumes += 1
                st.aero("mission", "command", "START", timeout_s=30)
            time.sleep(1.0)
    finally:
        out = _finish(fly, 30)
    return fly.returncode, out, resumes


def _record(st, base: Path) -> subprocess.Popen:
    """`aero record` of what `aero eval objects --replay` needs (its inputs; the images by --images)
    and what it scores against, on the stack's sim time; returns once it is subscribed."""
    log = base / "record.log"
    keys = [k for k in REPLAY_INPUTS if not k.endswith("/image")] + ["perception/objects", "sim/truth/state"]
    with open(log, "wb") as out:
        rec = subprocess.Popen(aero_argv() + ["record", "--preset", "none", "--images", "--sim-time", "-o",
                                              str(base / "rec"), *keys], env=clean_env(st.endpoint),
                               stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    wait_until(lambda: "recording " in log.read_text() or rec.poll() is not None, 30, "aero record subscribed")
    assert rec.poll() is None, log.read_text()
    return rec


def _replay_hint(base: Path, rec_code: int | None) -> str:
    files = sorted((base / "rec").glob("*.mcap"))
    if rec_code != 0 or not files:
        return f"no replayable recording (aero record exit {rec_code}): {(base / 'record.log').read_text()[-2000:]}"
    return "inputs recorded; replay with: " + " && ".join(
        f"aero eval objects --replay {f} --scenario village" for f in files)


def test_search_flight_finds_every_target_once_where_it_is(stack, tmp_path):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack(SERVICES, extra_args=[
        "--scenario", "village", "--sensors", "camera", "--speed", str(SPEED), "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}"], timeout_s=60)
    st.wait_flight_ready(90)
    wait_for_message(st.session, "perception/detections", Detection2DArray, timeout_s=60)
    rec = _record(st, tmp_path)
    out = tmp_path / "objects.json"
    ev = _popen(st, "eval", "objects", "--live", "--scenario", "village", "--until-landed", "--duration", "2000",
               "--json", str(out))
    try:
        time.sleep(2.0)
        code, fly_out, resumes = _fly_resuming(st, 1800)
        assert code == 0, f"fly exit {code}\n{fly_out}\n{st.describe()}"
        log = _finish(ev, 60)
    finally:
        if ev.poll() is None:
            ev.kill()
        hint = _replay_hint(tmp_path, interrupt(rec, 60))
    print(f"{fly_out}\nresumed {resumes} holds\n{log}\n{hint}")
    assert ev.returncode == 0, f"{log}\n{hint}"
    res = json.loads(out.read_text())
    assert {c: res["classes"][c]["targets"] for c in ("person", "car", "truck", "bicycle")} == \
        {"person": 6, "car": 3, "truck": 1, "bicycle": 2}
    assert unmet_goals(res) == [], f"{log}\n{hint}"
