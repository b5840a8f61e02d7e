"""The objects service on a real stack (`aero up --sensors camera`: sim rendering the stereo pair,
fmu, the bundled detector, objects, gcs): a person and a car standing a few metres ahead of the
landed vehicle become confirmed tracks of their class within 1 m of where the world put them,
each once, with lat/lon about the FC's home; diagnostics/objects reports the per-frame cost; a
ground station on UDP hears each as a STATUSTEXT and sees it as an ADS-B contact at that lat/lon.
`aero eval objects` then holds this short pass to the search flight's per-object goals (each target
found exactly once, no false track living > 2 s, position error median < 0.5 m and p95 < 1.5 m, the
service's CPU per frame); test_objects_search_flight.py (opt-in) flies the whole village search."""
from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as M

from aerotest import free_udp_port, wait_for_message, wait_until

from aeroperception.schemas import (
    DiagnosticStatus, HomePosition, ObjectEvent, TrackedObjectArray, decode,
)
from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.sim.world.scenario import load_scenario
from aeroperception.services.sim.world.scene import get_scene
from aeroperception.tools.eval.objects import unmet_goals

pytestmark = pytest.mark.timeout(180)

SCENARIO = """\
name: near_targets
description: Flat field; a person and a car a few metres ahead of the vehicle (stereo and ground ray both in range).
seed: 1
ground: {size_m: [100, 100], slope_deg: 0, material: grass}
start: {position_m: [0, 0], height_agl_m: 0, yaw_deg: 0}
objects:
  - {type: tree, position_m: [30, 12], height_m: 8}
targets:
  - {class: person, position_m: [7, 1], yaw_deg: 90}
  - {class: car, position_m: [11, -3], yaw_deg: 30}
sensors:
  camera: {width: 640, height: 480, rate_hz: 20, hfov_deg: 90, stereo: true, baseline_m: 0.08, pitch_down_deg: 10}
  imu: {rate_hz: 200}
"""


class GroundStation:
    """A UDP port gcs sends to: STATUSTEXTs and ADSB_VEHICLEs as they arrive (bounded by stop())."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.texts: list[str] = []
        self.contacts: dict[str, object] = {}
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        mav = M.MAVLink(None)
        mav.robust_parsing = True
        while self.running:
            try:
                data = self.sock.recv(65535)
            except OSError:
                continue
            for m in mav.parse_buffer(bytearray(data)) or []:
                if m.get_type() == "STATUSTEXT":
                    self.texts.append(m.text)
                elif m.get_type() == "ADSB_VEHICLE":
                    self.contacts[m.callsign.rstrip("\x00")] = m

    def stop(self):
        self.running = False
        self.thread.join(2.0)
        self.sock.close()


def test_targets_in_view_become_confirmed_tracks_at_their_true_positions(stack, tmp_path):
    path = tmp_path / "near_targets.yaml"
    path.write_text(SCENARIO)
    truth = {b.class_name: b.center_enu_m for b in get_scene(load_scenario(str(path))).target_boxes}
    fcu, sim_bind, gcs_port = free_udp_port(), free_udp_port(), free_udp_port()
    gs = GroundStation()
    try:
        st = stack(["sim", "fmu", "detector", "objects", "gcs"], extra_args=[
            "--scenario", str(path), "--sensors", "camera", "--fcu-url", f"udpin:127.0.0.1:{fcu}",
            "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
            "--arg", f"gcs:--local-port={gcs_port}", "--arg", f"gcs:--remote-port={gs.port}",
            "--arg", "gcs:--bind-ip=127.0.0.1"], timeout_s=60)
        check_objects(st, gs, truth)
        check_eval(st, path, tmp_path)
    finally:
        gs.stop()


def check_eval(st, scenario, tmp_path) -> None:
    """`aero eval objects --live` on the same stack: the search flight's per-object goals hold."""
    out = tmp_path / "eval.json"
    r = st.aero("eval", "objects", "--live", "--scenario", str(scenario), "--duration", "2", "--json", str(out),
                timeout_s=60)
    assert r.returncode == 0, r.stderr
    print(r.stdout)
    res = json.loads(out.read_text())
    assert {c: res["classes"][c]["found"] for c in ("person", "car")} == {"person": 1, "car": 1}, r.stdout
    assert unmet_goals(res) == [], r.stdout


def check_objects(st, gs: GroundStation, truth: dict) -> None:
    events: list[ObjectEvent] = []                        # list.append: safe from zenoh's thread
    sub = st.session.declare_subscriber("perception/objects/events",
                                        lambda s: events.append(decode(s.payload.to_bytes(), ObjectEvent)))
    try:
        wait_until(lambda: {"person", "car"} <= {e.object.class_name for e in list(events)
                                                 if e.event == ObjectEvent.CONFIRMED},
                   45, "confirmed person and car tracks")
        time.sleep(2.0)                                   # a few more frames refine the estimates
        latest = wait_for_message(st.session, "perception/objects", TrackedObjectArray, timeout_s=5)
        home = wait_for_message(st.session, "fmu/out/home_position", HomePosition, timeout_s=5)
        diag = wait_for_message(st.session, "diagnostics/objects", DiagnosticStatus,
                                lambda m: "frame_cpu_ms_p50" in m.values, timeout_s=5)
    except AssertionError as e:
        raise AssertionError(f"{e}\nevents: {events}\n{st.describe()}") from None
    finally:
        sub.undeclare()
    objs = [o for o in latest.objects if o.confirmed]
    confirmed = [e for e in events if e.event == ObjectEvent.CONFIRMED]
    print(f"objects: {[(o.track_id, o.class_name, o.hits, round(o.range_m, 1), o.position_m) for o in objs]}; "
          f"diagnostics {dict(diag.values)}")
    for cls in ("person", "car"):
        mine = [o for o in objs if o.class_name == cls]
        assert len(mine) == 1, f"{cls}: {len(mine)} confirmed tracks (exactly one expected): {mine}"
        o = mine[0]
        err = np.linalg.norm(o.position_m.to_array()[:2] - truth[cls][:2])
        assert err < 1.0, f"{cls} track at {o.position_m}, truth {truth[cls]}: {err:.2f} m"
        assert sum(e.object.class_name == cls for e in confirmed) == 1
        assert o.latitude_deg is not None
        north, east = MapProjection(home.latitude_deg, home.longitude_deg).project(o.latitude_deg, o.longitude_deg)
        assert abs(east + home.position_m.x - o.position_m.x) < 0.01 and abs(north + home.position_m.y - o.position_m.y) < 0.01
        # The ground station: told once, and shown on the map where the track is.
        wait_until(lambda: f"{cls.upper()}{o.track_id}" in gs.contacts, 5, f"ADSB_VEHICLE {cls.upper()}{o.track_id}")
        told = [t for t in list(gs.texts) if t.startswith(f"Object: {cls} #{o.track_id} at ")]
        assert len(told) == 1, list(gs.texts)
        c = gs.contacts[f"{cls.upper()}{o.track_id}"]
        assert abs(c.lat * 1e-7 - o.latitude_deg) < 2e-6 and abs(c.lon * 1e-7 - o.longitude_deg) < 3e-6
    assert float(diag.values["frame_cpu_ms_p50"]) < 5.0, dict(diag.values)
