"""`aero bench flight`: the hot path, state -> planner -> fmu -> SET_POSITION_TARGET_LOCAL_NED.

The whole sim profile runs (`aero up` as a child, its MAVLink re-routed through a tap in this
process). The tap timestamps each LOCAL_POSITION_NED on its way from the vehicle to fmu and the
first SET_POSITION_TARGET_LOCAL_NED that fmu sends back: that interval covers MAVLink decode,
ENU conversion, state/vehicle over Zenoh, the planner, the setpoint over Zenoh and the MAVLink
encode. Baseline, same run: two raw Zenoh one-way hops (the minimum the process split costs).
Also reported: the planner's 50 Hz deadline-loop period error and the setpoint gaps on the wire.
"""
from __future__ import annotations

import json
import os
import select
import socket
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from aeroperception.schemas import DiagnosticStatus, MissionCommand, Reply, SchemaError, decode
from aeroperception.services.runtime.node import CallError, call
from aeroperception.services.runtime.service import SWITCH_INTERVAL_S
from aeroperception.services.runtime.session import make_config, open_session

from .bench_pubsub import measure

LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED = 32, 84


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _msgid(pkt: bytes) -> int | None:
    if len(pkt) >= 10 and pkt[0] == 0xFD:
        return pkt[7] | pkt[8] << 8 | pkt[9] << 16
    if len(pkt) >= 6 and pkt[0] == 0xFE:
        return pkt[5]
    return None


class Tap:
    """UDP relay sim <-> fmu that timestamps the hot path."""

    def __init__(self, from_sim_port: int, fmu_port: int):
        self.a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.a.bind(("127.0.0.1", from_sim_port))
        self.b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.b.bind(("127.0.0.1", 0))
        self.fmu = ("127.0.0.1", fmu_port)
        self.sim_addr = None
        self.pending: float | None = None
        self.latency_ms: list[float] = []
        self.setpoint_t: list[float] = []
        self.lpn_t: list[float] = []
        self.recording = False
        self.stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self.stop.is_set():
            ready, _, _ = select.select([self.a, self.b], [], [], 0.1)
            for s in ready:
                pkt, addr = s.recvfrom(65535)
                now = time.perf_counter()
                if s is self.a:
                    self.sim_addr = addr
                    if _msgid(pkt) == LOCAL_POSITION_NED:
                        self.pending = now
                        if self.recording:
                            self.lpn_t.append(now)
                    self.b.sendto(pkt, self.fmu)
                else:
                    if _msgid(pkt) == SET_POSITION_TARGET_LOCAL_NED and self.recording:
                        self.setpoint_t.append(now)
                        if self.pending is not None:
                            self.latency_ms.append((now - self.pending) * 1e3)
                            self.pending = None
                    if self.sim_addr:
                        self.a.sendto(pkt, self.sim_addr)


def scheduling_line(log_dir: str) -> str:
    """What `aero up` printed about the priorities it gave (its "scheduling:" line)."""
    try:
        text = open(os.path.join(log_dir, "aero-up.out")).read()
    except OSError:
        return "unknown"
    lines = [ln for ln in text.splitlines() if ln.startswith("aero up: scheduling: ")]
    return lines[-1].removeprefix("aero up: scheduling: ") if lines else "unknown"


def breakdown(tap: Tap, seen: dict[str, list[float]]) -> dict[str, np.ndarray]:
    """Split each hot-path sample at the state/vehicle and setpoint arrivals seen here."""
    ins = np.array(tap.lpn_t)
    state, sp, out = np.array(seen["state"]), np.array(seen["setpoint"]), np.array(tap.setpoint_t)
    a, b, c = [], [], []
    for t0 in ins:
        i = np.searchsorted(state, t0)
        if i >= len(state):
            break
        j = np.searchsorted(sp, state[i])
        k = np.searchsorted(out, sp[j]) if j < len(sp) else len(out)
        if k >= len(out) or out[k] - t0 > 0.015:
            continue
        a.append(state[i] - t0)
        b.append(sp[j] - state[i])
        c.append(out[k] - sp[j])
    ms = lambda v: np.array(v) * 1e3  # noqa: E731
    return {"LOCAL_POSITION_NED -> state/vehicle seen": ms(a), "state/vehicle -> setpoint seen": ms(b),
            "setpoint seen -> SET_POSITION_TARGET sent": ms(c)}


def run(duration_s: float = 20.0, sensors: str = "none", priorities: bool = True) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL_S)  # the tap must not wait for the GIL either
    router_port, sim_tx, fmu_rx, sim_bind = _free_port(), _free_port(), _free_port(), _free_port()
    tap = Tap(sim_tx, fmu_rx)
    endpoint = f"tcp/127.0.0.1:{router_port}"
    log_dir = tempfile.mkdtemp(prefix="aero-bench-flight-")
    up_out = open(os.path.join(log_dir, "aero-up.out"), "wb")
    up = subprocess.Popen([sys.executable, "-m", "aeroperception.tools.cli", "up", "--listen", endpoint,
                           "--log-dir", log_dir, "--fcu-url", f"udpin:127.0.0.1:{fmu_rx}",
                           "--arg", f"sim:--target=127.0.0.1:{sim_tx}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
                           "--arg", f"sim:--sensors={sensors}"],
                          stdout=up_out, stderr=subprocess.STDOUT,
                          env=dict(os.environ, AERO_PRIORITIES="on" if priorities else "off"))
    session = None
    try:
        session = open_session(make_config(connect=endpoint), max_wait_s=10)
        last_diag: dict[str, DiagnosticStatus] = {}

        def on_diag(s) -> None:
            try:
                d = decode(s.payload.to_bytes(), DiagnosticStatus)
            except SchemaError:
                return
            last_diag[d.name] = d

        session.declare_subscriber("diagnostics/planner", on_diag)
        session.declare_subscriber("diagnostics/sim", on_diag)  # render rates: what priorities cost sensors
        # Breakdown: when this process sees the state and the setpoint (same router, so each
        # stamp is one Zenoh hop after the service published it).
        seen: dict[str, list[float]] = {"state": [], "setpoint": []}
        session.declare_subscriber("state/vehicle", lambda _s: tap.recording and seen["state"].append(time.perf_counter()))
        session.declare_subscriber("fmu/in/trajectory_setpoint",
                                   lambda _s: tap.recording and seen["setpoint"].append(time.perf_counter()))
        deadline = time.monotonic() + 30
        while True:  # wait for fmu to have the vehicle, then take off and hover
            try:
                r = call(session, "mission/srv/command", MissionCommand(command="TAKEOFF"), Reply, 5.0)
                if r.success:
                    break
            except CallError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"stack did not come up (logs: {log_dir})")
            time.sleep(1.0)
        time.sleep(8.0)  # climb, settle into OFFBOARD hover
        tap.latency_ms.clear()
        tap.recording = True
        time.sleep(duration_s)
        tap.recording = False
        lat = np.array(tap.latency_ms)
        stages = breakdown(tap, seen)
        gaps = np.diff(np.array(tap.setpoint_t)) * 1e3
        diag = last_diag["planner"].values if "planner" in last_diag else {}
        sim_diag = last_diag["sim"].values if "sim" in last_diag else {}
        sched = scheduling_line(log_dir)
        try:
            call(session, "mission/srv/command", MissionCommand(command="LAND"), Reply, 5.0)
        except CallError:
            pass
    finally:
        if session is not None:
            session.close()
        up.terminate()
        try:
            up.wait(10)
        except subprocess.TimeoutExpired:
            up.kill()
        up_out.close()
        tap.stop.set()
    router = make_config(mode="router", listen=[f"tcp/127.0.0.1:{_free_port()}"])
    router.insert_json5("scouting/delay", "0")
    router.insert_json5("connect/endpoints", "[]")
    import zenoh

    r = zenoh.open(router)
    try:
        raw = measure(json.loads(router.get_json("listen/endpoints"))[0], "raw", "state", 500)
    finally:
        r.close()
    base = 2 * float(np.median(raw))
    print(f"hot path LOCAL_POSITION_NED in -> SET_POSITION_TARGET_LOCAL_NED out, whole sim profile "
          f"(sensors={sensors}), {duration_s:.0f} s hover, {os.cpu_count()} cores")
    print(f"scheduling: {sched}")
    print(f"{'metric':<44} {'n':>6} {'median_ms':>10} {'p99_ms':>8} {'x_base':>7}")
    print(f"{'hot path latency':<44} {len(lat):>6} {np.median(lat):>10.3f} {np.percentile(lat, 99):>8.3f} "
          f"{np.median(lat) / base:>7.2f}")
    print(f"{'baseline: 2 raw zenoh one-way hops':<44} {len(raw):>6} {base:>10.3f} {2 * np.percentile(raw, 99):>8.3f} "
          f"{1.0:>7.2f}")
    for name, arr in stages.items():
        if len(arr):
            print(f"{'  ' + name:<44} {len(arr):>6} {np.median(arr):>10.3f} {np.percentile(arr, 99):>8.3f} {'':>7}")
    print(f"{'setpoint gap on the wire (50 Hz = 20 ms)':<44} {len(gaps):>6} {np.median(gaps):>10.3f} "
          f"{np.percentile(gaps, 99):>8.3f} {'':>7}")
    print(f"{'planner deadline-loop period error':<44} {diag.get('loop[setpoint].ticks', '-'):>6} "
          f"{float(diag.get('loop[setpoint].period_error_p50_ms', 'nan')):>10.3f} "
          f"{float(diag.get('loop[setpoint].period_error_p99_ms', 'nan')):>8.3f} {'':>7}")
    rendered = [f"{k.removesuffix('_rate_hz')} {v} Hz" for k, v in sim_diag.items() if k.endswith("_rate_hz")]
    if rendered:
        print(f"sensors rendered meanwhile (sim diagnostics): {', '.join(rendered)}")
    return 0
