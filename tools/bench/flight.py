"""`aero bench flight`: the hot path, state -> planner -> fmu -> SET_POSITION_TARGET_LOCAL_NED.

The whole sim profile runs (`aero up` as a child, its MAVLink re-routed through a tap in this
process). The tap timestamps each LOCAL_POSITION_NED on its way from the vehicle to fmu and the
first SET_POSITION_TARGET_LOCAL_NED that fmu sends back: that interval covers MAVLink decode,
ENU conversion, state/vehicle over Zenoh, the planner, the setpoint over Zenoh and the MAVLink
encode. Baseline, same run: two raw Zenoh one-way hops (the minimum the process split costs).
Also reported: the planner's 50 Hz deadline-loop period error, the setpoint gaps on the wire and,
beside them, the sim's own LOCAL_POSITION_NED gaps (the planner answers each state, so a late
state is a late setpoint). Stamps are the kernel's receive times at the tap (see Tap).
"""
from __future__ import annotations

import json
import os
import shutil
import select
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from aeroperception.schemas import DiagnosticStatus, MissionCommand, Reply, SchemaError, decode
from aeroperception.services.runtime.node import CallError, call
from aeroperception.services.runtime.service import SWITCH_INTERVAL_S
from aeroperception.services.runtime.supervision import Priority, apply_priority
from aeroperception.services.runtime.session import make_config, open_session

from .pubsub import measure
from aeroperception.tools.harness import free_port, free_udp_port, msgid

LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED = 32, 84


SO_TIMESTAMPNS = 35      # Linux: the kernel's receive time of each datagram (not in Python's socket module)
TAP_PRIORITY = Priority(realtime=20)   # the wire the tap stands in for never waits for a CPU


def _kernel_stamp_s(ancillary: list, fallback_s: float) -> float:
    """The datagram's kernel receive time (CLOCK_REALTIME, s) from recvmsg's ancillary data."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
            sec, ns = struct.unpack("qq", data[:16])
            return sec + ns * 1e-9
    return fallback_s


class Tap:
    """UDP relay sim <-> fmu that timestamps the hot path.

    Every stamp is the kernel's receive time of the datagram (SO_TIMESTAMPNS), so the relay's
    own wake-up delay is not counted as fmu's: the setpoint's stamp is when it reached the
    wire's end; the state's is when it left the relay for fmu (`forward_ms` is the relay's
    delay, reported separately). With priorities on, the relay thread runs at the hot path's
    SCHED_RR priority: at load 25 a nice-0 relay starved the link into a stale FC."""

    def __init__(self, from_sim_port: int, fmu_port: int, priority: bool = True):
        self.a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.a.bind(("127.0.0.1", from_sim_port))
        self.b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.b.bind(("127.0.0.1", 0))
        for s in (self.a, self.b):
            s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.fmu = ("127.0.0.1", fmu_port)
        self.sim_addr = None
        self.priority = priority
        self.sched = ""
        self.pending: float | None = None
        self.latency_ms: list[float] = []
        self.pairs: list[tuple[float, float]] = []   # (state relayed to fmu, the setpoint that followed)
        self.forward_ms: list[float] = []   # state: kernel receive -> relayed to fmu
        self.setpoint_t: list[float] = []
        self.lpn_t: list[float] = []        # kernel receive time of each LOCAL_POSITION_NED from the sim
        self.recording = False
        self.stop = threading.Event()
        threading.Thread(target=self._run, name="tap", daemon=True).start()

    def _run(self) -> None:
        if self.priority:
            self.sched = apply_priority(0, TAP_PRIORITY)   # pid 0: this thread
        while not self.stop.is_set():
            ready, _, _ = select.select([self.a, self.b], [], [], 0.1)
            for s in ready:
                try:
                    pkt, anc, _flags, addr = s.recvmsg(65535, 64)
                except OSError:   # ICMP refused from a send before fmu (or the sim) had bound its port
                    continue
                now = time.time()
                rx = _kernel_stamp_s(anc, now)
                if s is self.a:
                    self.sim_addr = addr
                    self.b.sendto(pkt, self.fmu)
                    if msgid(pkt) == LOCAL_POSITION_NED:
                        self.pending = time.time()
                        if self.recording:
                            self.lpn_t.append(rx)
                            self.forward_ms.append((self.pending - rx) * 1e3)
                else:
                    if self.sim_addr:
                        self.a.sendto(pkt, self.sim_addr)
                    if msgid(pkt) == SET_POSITION_TARGET_LOCAL_NED and self.recording:
                        self.setpoint_t.append(rx)
                        if self.pending is not None:
                            self.latency_ms.append((rx - self.pending) * 1e3)
                            self.pairs.append((self.pending, rx))
                            self.pending = None


def scheduling_line(log_dir: str) -> str:
    """What `aero up` printed about the priorities it gave (its "scheduling:" line)."""
    try:
        text = open(os.path.join(log_dir, "aero-up.out")).read()
    except OSError:
        return "unknown"
    lines = [ln for ln in text.splitlines() if ln.startswith("aero up: scheduling: ")]
    return lines[-1].removeprefix("aero up: scheduling: ") if lines else "unknown"


def breakdown(tap: Tap, seen: dict[str, list[float]]) -> dict[str, np.ndarray]:
    """Split each hot-path sample (state relayed to fmu .. its setpoint on the wire) at the first
    state/vehicle and then setpoint seen here inside it. The bench hears the setpoint in parallel
    with fmu (one router hop each), so the last stage can be slightly negative."""
    state, sp = np.array(seen["state"]), np.array(seen["setpoint"])
    a, b, c = [], [], []
    for t0, t1 in tap.pairs:
        i = np.searchsorted(state, t0)
        if i >= len(state) or state[i] > t1:
            continue
        j = np.searchsorted(sp, state[i])
        if j >= len(sp) or sp[j] > t1 + 0.002:
            continue
        a.append(state[i] - t0)
        b.append(sp[j] - state[i])
        c.append(t1 - sp[j])
    ms = lambda v: np.array(v) * 1e3  # noqa: E731
    return {"LOCAL_POSITION_NED -> state/vehicle seen": ms(a), "state/vehicle -> setpoint seen": ms(b),
            "setpoint seen -> SET_POSITION_TARGET sent": ms(c)}


class HoverRun:
    """The sim profile (`aero up` as a child, fmu's MAVLink through a Tap) with the vehicle taken
    off and hovering: `begin()` .. `end()` is one measured window of the hot path.
    `aero bench stack` measures its whole-stack figures in the same window."""

    def __init__(self, sensors: str = "none", priorities: bool = True, up_args: tuple[str, ...] = ()):
        router_port, (sim_tx, fmu_rx, sim_bind) = free_port(), (free_udp_port() for _ in range(3))
        self.tap = Tap(sim_tx, fmu_rx, priorities)
        self.endpoint = f"tcp/127.0.0.1:{router_port}"
        self.log_dir = tempfile.mkdtemp(prefix="aero-bench-flight-")
        self._up_out = open(os.path.join(self.log_dir, "aero-up.out"), "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "aeroperception.tools.cli", "up", "--listen", self.endpoint,
             "--log-dir", self.log_dir, "--fcu-url", f"udpin:127.0.0.1:{fmu_rx}",
             "--arg", f"sim:--target=127.0.0.1:{sim_tx}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
             "--arg", f"sim:--sensors={sensors}", *up_args],
            stdout=self._up_out, stderr=subprocess.STDOUT,
            env=dict(os.environ, AERO_PRIORITIES="on" if priorities else "off"))
        self.session = None
        self.last_diag: dict[str, DiagnosticStatus] = {}
        # Breakdown: when this process sees the state and the setpoint (same router, so each
        # stamp is one Zenoh hop after the service published it).
        self.seen: dict[str, list[float]] = {"state": [], "setpoint": []}

    def pids(self) -> dict[str, int]:
        """{service: pid} as `aero up` recorded them."""
        try:
            return json.loads(open(os.path.join(self.log_dir, "pids.json")).read())
        except (OSError, ValueError):
            return {}

    def _open_session(self, timeout_s: float):
        """The bench's own session (state and setpoint arrival stamps of the breakdown), opened
        from a thread at the tap's priority so Zenoh's threads inherit it: at nice 0 under load
        those callbacks, not the services, set the breakdown's p99."""
        box: list = [None]

        def opener() -> None:
            if self.tap.priority:
                apply_priority(0, TAP_PRIORITY)
            box[0] = open_session(make_config(connect=self.endpoint), max_wait_s=timeout_s)

        t = threading.Thread(target=opener, name="bench-session")
        t.start()
        t.join()
        return box[0]

    def take_off(self, timeout_s: float = 30.0, settle_s: float = 8.0) -> None:
        """Wait for the stack to have the vehicle, take off, settle into the OFFBOARD hover."""
        deadline = time.monotonic() + timeout_s
        self.session = self._open_session(timeout_s)
        if self.session is None:
            raise RuntimeError(f"aero up's router did not answer within {timeout_s:.0f} s (logs: {self.log_dir})")

        def on_diag(s) -> None:
            try:
                d = decode(s.payload.to_bytes(), DiagnosticStatus)
            except SchemaError:
                return
            self.last_diag[d.name] = d

        self.session.declare_subscriber("diagnostics/*", on_diag)
        tap = self.tap
        self.session.declare_subscriber("state/vehicle",
                                        lambda _s: tap.recording and self.seen["state"].append(time.time()))
        self.session.declare_subscriber("fmu/in/trajectory_setpoint",
                                        lambda _s: tap.recording and self.seen["setpoint"].append(time.time()))
        while True:
            try:
                r = call(self.session, "mission/srv/command", MissionCommand(command="TAKEOFF"), Reply, 5.0)
                if r.success:
                    break
            except CallError:
                pass
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise RuntimeError(f"stack did not come up (logs: {self.log_dir})")
            time.sleep(1.0)
        time.sleep(settle_s)  # climb, settle into OFFBOARD hover
        self.wait_for_renderers()

    def wait_for_renderers(self, timeout_s: float = 120.0) -> list[str]:
        """Block until every sim renderer has delivered frames (the load this bench is about),
        at most `timeout_s`; the renderers still silent (also printed). At load 20 the nice-10
        render processes took ~45 s to start, and a window before that measured no sensor load."""
        deadline = time.monotonic() + timeout_s
        while True:
            values = self.last_diag.get("sim", DiagnosticStatus()).values
            silent = [k.removesuffix("_frames") for k, v in values.items() if k.endswith("_frames") and v == "0"]
            if not silent and values or time.monotonic() > deadline or self.proc.poll() is not None:
                break
            time.sleep(0.5)
        if silent:
            print(f"warning: no frames rendered yet by {', '.join(silent)} after {timeout_s:.0f} s: measuring without them")
        return silent

    def begin(self) -> None:
        for samples in (self.tap.latency_ms, self.tap.pairs, self.tap.forward_ms, self.tap.lpn_t, self.tap.setpoint_t):
            samples.clear()
        self.tap.recording = True

    def end(self) -> "HotPath":
        self.tap.recording = False
        diag = self.last_diag.get("planner", DiagnosticStatus()).values
        return HotPath(lat=np.array(self.tap.latency_ms), stages=breakdown(self.tap, self.seen),
                       gaps=np.diff(np.array(self.tap.setpoint_t)) * 1e3,
                       state_gaps=np.diff(np.array(self.tap.lpn_t)) * 1e3, forward=np.array(self.tap.forward_ms),
                       period_error=(diag.get("loop[setpoint].ticks", "-"),
                                     float(diag.get("loop[setpoint].period_error_p50_ms", "nan")),
                                     float(diag.get("loop[setpoint].period_error_p99_ms", "nan"))),
                       sched=scheduling_line(self.log_dir))

    def close(self) -> None:
        """Land (best effort) and stop the stack; its logs are removed unless an error is on its
        way out (its message names the folder)."""
        try:
            if self.session is not None:
                try:
                    call(self.session, "mission/srv/command", MissionCommand(command="LAND"), Reply, 5.0)
                except CallError:
                    pass
                self.session.close()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            self._up_out.close()
            self.tap.stop.set()
            if sys.exc_info()[0] is None:
                shutil.rmtree(self.log_dir, ignore_errors=True)


@dataclass
class HotPath:
    """One window's hot-path figures (ms)."""

    lat: np.ndarray
    stages: dict[str, np.ndarray]
    gaps: np.ndarray
    period_error: tuple[str, float, float]   # planner loop: ticks, p50, p99
    sched: str
    state_gaps: np.ndarray = field(default_factory=lambda: np.zeros(0))  # LOCAL_POSITION_NED from the sim
    forward: np.ndarray = field(default_factory=lambda: np.zeros(0))     # the tap's relay delay (not in lat)

    def rows(self) -> list[tuple[str, int | str, float, float]]:
        """(metric, n, median_ms, p99_ms) for the latency, its stages, the gap and the loop error."""
        out = [("hot path latency", len(self.lat), _q(self.lat, 50), _q(self.lat, 99))]
        out += [("  " + name, len(a), _q(a, 50), _q(a, 99)) for name, a in self.stages.items() if len(a)]
        out.append(("setpoint gap on the wire (50 Hz = 20 ms)", len(self.gaps), _q(self.gaps, 50), _q(self.gaps, 99)))
        if len(self.state_gaps):   # the sim's own jitter: a late state is a late setpoint
            out.append(("  sim's LOCAL_POSITION_NED gap (50 Hz)", len(self.state_gaps), _q(self.state_gaps, 50),
                         _q(self.state_gaps, 99)))
        if len(self.forward):
            out.append(("  tap relay delay (not in the hot path)", len(self.forward), _q(self.forward, 50),
                        _q(self.forward, 99)))
        out.append(("planner deadline-loop period error", *self.period_error))
        return out


def _q(a: np.ndarray, pct: float) -> float:
    return float(np.percentile(a, pct)) if len(a) else float("nan")


def raw_hops_baseline(n: int = 500) -> np.ndarray:
    """One-way raw Zenoh latencies (ms) through a router of their own, measured now."""
    router = make_config(mode="router", listen=[f"tcp/127.0.0.1:{free_port()}"])
    router.insert_json5("scouting/delay", "0")
    router.insert_json5("connect/endpoints", "[]")
    import zenoh

    r = zenoh.open(router)
    try:
        return measure(json.loads(router.get_json("listen/endpoints"))[0], "raw", "state", n)
    finally:
        r.close()


def run(duration_s: float = 20.0, sensors: str = "none", priorities: bool = True, links: str = "direct") -> int:
    sys.setswitchinterval(SWITCH_INTERVAL_S)  # the tap must not wait for the GIL either
    hover = HoverRun(sensors, priorities, ("--links", links))
    try:
        hover.take_off()
        hover.begin()
        time.sleep(duration_s)
        hp = hover.end()
        sim_diag = hover.last_diag.get("sim", DiagnosticStatus()).values
    finally:
        hover.close()
    raw = raw_hops_baseline()
    base = 2 * float(np.median(raw))
    print(f"hot path LOCAL_POSITION_NED in -> SET_POSITION_TARGET_LOCAL_NED out, whole sim profile "
          f"(sensors={sensors}, {links} links), {duration_s:.0f} s hover, {os.cpu_count()} cores")
    print(f"scheduling: {hp.sched}, bench tap {hover.tap.sched or 'nice 0'}")
    print(f"{'metric':<44} {'n':>6} {'median_ms':>10} {'p99_ms':>8} {'x_base':>7}")
    rows = hp.rows()
    name, n, med, p99 = rows[0]
    print(f"{name:<44} {n:>6} {med:>10.3f} {p99:>8.3f} {med / base:>7.2f}")
    print(f"{'baseline: 2 raw zenoh one-way hops':<44} {len(raw):>6} {base:>10.3f} {2 * np.percentile(raw, 99):>8.3f} "
          f"{1.0:>7.2f}")
    for name, n, med, p99 in rows[1:]:
        print(f"{name:<44} {n:>6} {med:>10.3f} {p99:>8.3f} {'':>7}")
    rendered = [f"{k.removesuffix('_rate_hz')} {v} Hz" for k, v in sim_diag.items() if k.endswith("_rate_hz")]
    if rendered:
        print(f"sensors rendered meanwhile (sim diagnostics): {', '.join(rendered)}")
    return 0
