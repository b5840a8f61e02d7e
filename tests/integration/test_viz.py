"""viz on a short real flight (takeoff, goto, land through the mission service's actions) on the
sim stack with cameras (the lidar service is left out to keep CI lean; its adapters are
unit-tested): the view is served (web viewer + gRPC on
loopback) and saved as a .rrd at the same time.

- test_web_viewer_shows_the_live_stream_in_headless_chromium: Debian's Chromium (headless,
  software WebGL, loopback only) loads the served viewer while the stack streams; the screenshot
  (path printed) shows the viewer drawn with the vehicle's and the truth's tracks in their colours.
  For the check the viewer gets a blueprint with only the 3D scene and a small window: on two busy
  cores the default layout's camera views made each software-rendered screenshot take > 60 s.
- test_rrd_holds_the_flight_on_every_expected_entity: after the stack stops, the .rrd read back
  with Rerun's own reader (rerun.chunk.RrdReader) has data on each expected entity path over
  the flight's time range (stamps from the message headers).

One stack for the module; the flight runs once (fixture). Marked slow: it flies.
"""
from __future__ import annotations

import os
import time
import urllib.parse
from pathlib import Path

import numpy as np
import pytest

from aerotest import free_port, free_udp_port, wait_for_message, wait_until
from aeroperception.schemas import (
    DiagnosticStatus, GoalStatus, GoToPositionGoal, LandGoal, MissionStatus, TakeoffGoal, Vector3, VehicleState,
)
from aeroperception.services.runtime import ActionClient
from aeroperception.services.viz import adapters as A

pytestmark = pytest.mark.slow

SERVICES = ["sim", "fmu", "planner", "mission", "diagnostics", "viz"]   # lidar left out: ~1 core on CI
GOTO = (6.0, 0.0, 3.0)       # along the village street, people and cars ahead in the camera


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_action(st, name: str, goal, timeout_s: float):
    client = ActionClient(st.session, f"mission/action/{name}")
    try:
        g = client.send_goal(goal)
        assert g.success, f"{name} goal rejected: {g.message}"
        res = client.result(g.goal_id, timeout_s)
        assert res.status == GoalStatus.SUCCEEDED, f"{name}: {GoalStatus.name(res.status)} {res.message}"
    finally:
        client.close()


@pytest.fixture(scope="module")
def flight(stack_module, tmp_path_factory):
    out = tmp_path_factory.mktemp("viz")
    rrd = out / "flight.rrd"
    web, grpc = free_port(), free_port()
    fcu, sim_bind = free_udp_port(), free_udp_port()
    viz = [f"--param=web_port={web}", f"--param=grpc_port={grpc}", "--param=bind_ip=127.0.0.1",
           f"--param=save_path={rrd}"]
    st = stack_module(SERVICES, profile="viz", timeout_s=40, extra_args=[
        "--scenario", "village", "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
        *(a for v in viz for a in ("--arg", f"viz:{v}"))])
    try:
        wait_for_message(st.session, "state/vehicle", VehicleState, lambda m: m.connected, 20)
        wait_for_message(st.session, "mission/status", MissionStatus, timeout_s=10)
        # OFFBOARD needs the setpoint stream for a while before the switch (as in test_flight).
        wait_for_message(st.session, "diagnostics/fmu", DiagnosticStatus,
                         lambda d: int(d.values.get("setpoints_sent", 0)) > 100, 20)
        viz_pid = st.pids()["viz"]
        cpu0, t0 = cpu_s(viz_pid), time.monotonic()
        start_ns = time.time_ns()
        run_action(st, "takeoff", TakeoffGoal(target_altitude_m=3.0), 60)
        run_action(st, "goto", GoToPositionGoal(position_m=Vector3(x=GOTO[0], y=GOTO[1], z=GOTO[2])), 60)
        diag = wait_for_message(st.session, "diagnostics/viz", DiagnosticStatus, timeout_s=3)
        run_action(st, "land", LandGoal(), 60)
        end_ns = time.time_ns()
        viz_cpu = (cpu_s(viz_pid) - cpu0) / (time.monotonic() - t0)
        print(f"viz CPU over the flight: {100 * viz_cpu:.0f} % of one core; diagnostics: {dict(diag.values)}")
    except BaseException:
        print(st.describe())
        raise
    return dict(stack=st, rrd=rrd, web=web, grpc=grpc, start_ns=start_ns, end_ns=end_ns, diag=diag,
                viz_cpu=viz_cpu, out=out)


def test_viz_samples_and_never_queues_during_the_flight(flight):
    v = flight["diag"].values
    assert int(v["received"]) > int(v["logged"]) > 0, v
    assert int(v["sampled_out"]) > 0, v                    # 50 Hz state, 20 Hz cameras sampled down
    assert "dropped_busy" in v and "dropped_viewer_behind" in v
    assert flight["viz_cpu"] < 0.8, f"viz used {100 * flight['viz_cpu']:.0f} % of a core"


def test_web_viewer_shows_the_live_stream_in_headless_chromium(flight):
    import cv2

    from browser import headless_chromium, missing_tools, serve_files

    missing = missing_tools()
    assert not missing, f"{', '.join(missing)} not installed: deploy/install.sh installs chromium chromium-driver with the test extra"
    files = flight["out"] / "www"
    files.mkdir(exist_ok=True)
    scene_only_blueprint().save(APPLICATION_ID, str(files / "scene.rbl"))
    shot = flight["out"] / "web_viewer.png"
    t0 = time.monotonic()
    with serve_files(files) as files_port, headless_chromium(window=WINDOW) as browser:
        t_browser = time.monotonic() - t0
        url = (f"http://127.0.0.1:{flight['web']}/?url="
               + urllib.parse.quote(f"rerun+http://127.0.0.1:{flight['grpc']}/proxy", safe="")
               + "&url=" + urllib.parse.quote(f"http://127.0.0.1:{files_port}/scene.rbl", safe=""))
        browser.get(url)
        t_loaded = time.monotonic() - t0
        verdict, shots = {}, []

        def rendered():
            t = time.monotonic()
            png = browser.screenshot_png(timeout_s=30.0, total_s=120.0)
            shots.append(round(time.monotonic() - t, 1))
            shot.write_bytes(png)
            verdict.update(screen_verdict(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)))
            return verdict["ok"]

        try:
            wait_until(rendered, 150, "the web viewer to draw the live stream", interval_s=2.0)
        finally:
            print(f"web viewer: browser up in {t_browser:.1f} s, page loaded at {t_loaded:.1f} s, "
                  f"drawn {time.monotonic() - t0:.1f} s after the start; screenshot calls (s): {shots}; "
                  f"screenshot: {shot} ({verdict})")
            for line in browser.console()[-15:]:
                print("chromium console:", line.get("level"), line.get("message", "")[:300])


APPLICATION_ID = "aeroperception"    # viz's recording (ViewerSink): a blueprint applies to its application
WINDOW = (960, 600)                  # a quarter of the pixels of 1600x1000 to software-render


def scene_only_blueprint():
    """Only the 3D scene (ENU world), panels collapsed: what the check looks at, without the
    camera views and plots that cost the software renderer most of its time."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Spatial3DView(origin=A.WORLD, name="Scene (ENU)"), collapse_panels=True)


def screen_verdict(bgr: np.ndarray) -> dict:
    """The viewer is drawn (its top bar: text and icons, many colours; a blank page has one), and
    in the 3D scene below it the vehicle's and the truth's tracks (unlit lines, drawn in their
    logged colours) each cover some pixels, spread along a line (not a speck)."""
    h, w = bgr.shape[:2]
    top_colours = len(np.unique(bgr[:34].reshape(-1, 3) // 8, axis=0))
    scene = bgr[40:h - 40, 10:w - 10].astype(int)

    def track(rgb) -> tuple[int, int]:
        mask = np.abs(scene - np.array(rgb[::-1])).max(axis=2) < 40
        ys, xs = np.nonzero(mask)
        extent = max(int(np.ptp(xs)), int(np.ptp(ys))) if len(xs) else 0
        return int(mask.sum()), extent
    (vehicle_px, vehicle_extent), (truth_px, truth_extent) = track(A.VEHICLE_COLOR), track(A.TRUTH_COLOR)
    ok = (top_colours > 20 and vehicle_px > 30 and truth_px > 30
          and vehicle_extent > 40 and truth_extent > 40)
    return dict(ok=ok, top_colours=top_colours, vehicle_px=vehicle_px, truth_px=truth_px,
                vehicle_extent_px=vehicle_extent, truth_extent_px=truth_extent)


def test_rrd_holds_the_flight_on_every_expected_entity(flight):
    from aeroperception.services.viz.rrd import entity_spans

    st = flight["stack"]
    st.stop()                                   # viz finishes the file (footer) on SIGTERM
    rrd: Path = flight["rrd"]
    assert rrd.exists() and rrd.stat().st_size > 0, f"no {rrd}"
    spans = entity_spans(str(rrd))
    t0, t1 = flight["start_ns"], flight["end_ns"]
    expected = [
        "/world/vehicle", "/world/vehicle/body", "/world/trajectory/vehicle", "/world/truth/vehicle",
        "/world/trajectory/truth", "/world/vehicle/setpoint", "/world/mission/active_goal",
        "/camera/left/image", "/camera/right/image", "/camera/left/image/truth_boxes",
        "/series/altitude_m/vehicle", "/series/speed_mps/vehicle", "/series/battery_pct/remaining", "/logs/mission",
    ]
    problems = []
    for path in expected:
        s = spans.get(path)
        if s is None or s.first_ns is None:
            problems.append(f"{path}: no timed data")
        elif s.first_ns > t0 + 10e9 or s.last_ns < t1 - 10e9:
            problems.append(f"{path}: {s.rows} rows over {(s.first_ns - t0) / 1e9:+.1f} .. {(s.last_ns - t1) / 1e9:+.1f} s "
                            f"of the flight's start .. end")
    assert not problems, "\n".join(problems) + f"\nentities: {sorted(spans)}"
    assert spans["/world/vehicle/body/model"].rows >= 1                       # the static body model
    assert any(p.startswith("/series/loop_work_p99_ms/planner.") for p in spans), sorted(spans)  # loop timing
    assert any(p.startswith("/logs/diagnostics/") for p in spans), sorted(spans)
    # the pose is sampled down (10 Hz of 50) but covers the whole flight densely
    v = spans["/world/vehicle"]
    assert v.rows >= 5 * (t1 - t0) / 1e9, f"{v.rows} poses over {(t1 - t0) / 1e9:.0f} s"
