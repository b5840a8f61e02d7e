"""`aero chaos`: fault injection against a running sim stack, one fault per row, and a figures table.

Each row starts from the ground, flies a mission (survey_01 by default), injects one fault mid-leg
(kill -9 of a service, router kill, FC link loss, ground-station loss, SIGSTOP hang, clock jump;
FC reboot on the ground), observes what the stack and the vehicle do, and judges two things:
the row's expected outcome (issue 8 / ARCHITECTURE §8) and whether the vehicle stayed safe by the
simulator's ground truth (sim/truth/state): no ground impact at speed, inside the geofence, every
setpoint the flight controller received finite and inside the envelope, and at the end either
holding, landed and disarmed, or flying the mission normally.

The stack is this module's `SimStack`: `aero up --profile sim` on a free router port, a private
log dir and free MAVLink ports, with a `MavlinkTap` relaying sim <-> fmu in this process, so a
row can cut the FC link, inject commands to the FC (reboot) and check every
SET_POSITION_TARGET_LOCAL_NED fmu sends. tests/faults and `aero bench soak` use the same class.
Every process is stopped by its own pid (from aero up's pids.json), never by name.

A row whose fix is not in yet can be listed in EXPECTED_FIXED_BY (empty: every row is expected to pass).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zenoh
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import (
    Clock, DiagnosticStatus, GcsLink, Header, Imu, LoadMissionReply, LoadMissionRequest, MissionCommand,
    MissionStatus, Reply, SchemaError, SetModeReply, SetModeRequest, TrajectoryStatus, Vector3, VehicleState,
    decode, encode,
)
from aeroperception.services.mavlink import frames, px4
from aeroperception.services.runtime.node import LIVELINESS_ROOT, CallError, call, encoding_for
from aeroperception.services.runtime.session import make_config, open_session
from aeroperception.services.safety.geofence import Geofence

from .bench_flight import _msgid
from .cmd_up import fed_services
from .common import CliError

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MISSION = REPO / "examples" / "missions" / "survey_01.json"
SAFE_SETPOINT_SPEED_MPS = 20.0       # a setpoint faster than this at the FC is unsafe (issue 8 #5)
IMPACT_SPEED_MPS = 1.5               # touching the ground faster than this is an impact
AT_REST_MPS = 0.3

# Rows that fail on this branch until another branch's fix is merged (the lead removes entries).
EXPECTED_FIXED_BY: dict[str, str] = {}


# ---------------------------------------------------------------- processes


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago (TCP by default, SOCK_DGRAM for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def is_service_process(pid: int, name: str) -> bool:
    """Whether `pid` is (still) the process of service `name` (guards against reused pids)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return f"aeroperception.services.{name}".encode() in cmd


def clean_env() -> dict[str, str]:
    """This environment without AERO_* settings a developer may have exported."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERO_")}
    env["PYTHONUNBUFFERED"] = "1"
    return env


def stop_up(session: zenoh.Session | None, proc: subprocess.Popen | None, children: dict[str, int],
            timeout_s: float = 8.0) -> int | None:
    """Stop an `aero up`: close our session, SIGINT it (it stops its children), kill it if it
    hangs, then SIGKILL any child it left behind (by the pid it recorded; SIGCONT first, in case
    a fault left it stopped). Returns aero up's exit code."""
    if session is not None:
        try:
            session.close()
        except Exception:  # noqa: BLE001 - the router may be gone
            pass
    if proc is not None and proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)
    for name, pid in children.items():
        if is_service_process(pid, name):
            try:
                os.kill(pid, signal.SIGCONT)
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    return proc.returncode if proc is not None else None


def profile_services(profile: str = "sim") -> list[str]:
    from .cmd_up import load_profiles

    return list(load_profiles()[profile]["services"])


# ---------------------------------------------------------------- MAVLink tap


SET_POSITION_TARGET_LOCAL_NED = mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
_IGNORE = {  # type_mask bit -> field
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE: "x", mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE: "y",
    mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE: "z", mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE: "vx",
    mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE: "vy", mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE: "vz",
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE: "afx", mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE: "afy",
    mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE: "afz", mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE: "yaw",
    mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE: "yaw_rate",
}


def setpoint_problem(m, fence: Geofence) -> str | None:
    """Why a SET_POSITION_TARGET_LOCAL_NED the FC received is unsafe, or None: a used field not
    finite, a speed above SAFE_SETPOINT_SPEED_MPS, a position outside the fence (NED: z down)."""
    used = {f: getattr(m, f) for bit, f in _IGNORE.items() if not m.type_mask & bit}
    bad = [f for f, v in used.items() if not math.isfinite(v)]
    if bad:
        return f"non-finite {','.join(bad)}"
    v = [used.get(f, 0.0) for f in ("vx", "vy", "vz")]
    if math.hypot(*v) > SAFE_SETPOINT_SPEED_MPS:
        return f"speed {math.hypot(*v):.1f} m/s"
    if all(f in used for f in ("x", "y", "z")):
        east, north, up = m.y, m.x, -m.z
        if math.hypot(east, north) > fence.radius_m or up > fence.max_altitude_m or up < -1.0:
            return f"position ({east:.1f}, {north:.1f}, {up:.1f}) ENU outside the fence"
    return None


class MavlinkTap:
    """A UDP relay between the simulated FC and fmu, in this process.

    The sim sends to `sim_port`; the tap forwards to fmu's udpin port from a socket of its own
    and relays fmu's replies back. `cut` drops everything both ways (FC link loss); `to_fc`
    injects a message to the FC as if from the companion; every setpoint fmu sends is decoded
    and checked (`setpoints`, `unsafe`); `counts` per message id sim -> fmu give stream rates.
    """

    def __init__(self, sim_port: int, fmu_port: int, fence: Geofence | None = None):
        self.from_sim = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.from_sim.bind(("127.0.0.1", sim_port))
        self.to_fmu = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to_fmu.bind(("127.0.0.1", 0))
        self.fmu = ("127.0.0.1", fmu_port)
        self.fence = fence or Geofence()
        self.sim_addr: tuple[str, int] | None = None
        self.cut = threading.Event()
        self.lock = threading.Lock()
        self.setpoints: list[tuple[float, Any]] = []   # (monotonic, message) last few minutes
        self.unsafe: list[tuple[float, str]] = []
        self.setpoints_total = 0
        self.stamps: dict[int, list[float]] = {LOCAL_POSITION_NED: []}   # rx time of tracked ids
        self.acks: list[tuple[float, int, int]] = []   # (time, command, result) the FC sent
        # The FC's own view (LOCAL_POSITION_NED + HEARTBEAT) as VehicleState: the truth when
        # Zenoh is down (router kill); in the sim its estimate is the truth plus noise.
        self.fc_track: list[tuple[float, VehicleState]] = []
        self._fc_armed, self._fc_mode = False, ""
        self.dropped = 0
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.from_sim, self.to_fmu], [], [], 0.1)
            except (OSError, ValueError):
                return
            for s in ready:
                try:
                    pkt, addr = s.recvfrom(65535)
                except OSError:
                    continue
                now = time.monotonic()
                if self.cut.is_set():
                    self.dropped += 1
                    continue
                try:
                    if s is self.from_sim:
                        self.sim_addr = addr
                        mid = _msgid(pkt)
                        if mid in self.stamps:
                            with self.lock:
                                self.stamps[mid].append(now)
                                if len(self.stamps[mid]) > 20000:
                                    del self.stamps[mid][:10000]
                        if mid in (LOCAL_POSITION_NED, HEARTBEAT):
                            self._fc_state(pkt, now)
                        elif mid == COMMAND_ACK:
                            for m in self._parse(pkt):
                                with self.lock:
                                    self.acks.append((now, m.command, m.result))
                        self.to_fmu.sendto(pkt, self.fmu)
                    else:
                        if _msgid(pkt) == SET_POSITION_TARGET_LOCAL_NED:
                            self._check(pkt, now)
                        if self.sim_addr:
                            self.from_sim.sendto(pkt, self.sim_addr)
                except OSError:
                    pass

    def _parse(self, pkt: bytes) -> list:
        p = self._parser
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        try:
            msgs = p.parse_buffer(pkt) or []
        except Exception:  # noqa: BLE001 - a frame pymavlink cannot parse is nothing we track
            return []
        return [m for m in msgs if m is not None and m.get_type() != "BAD_DATA"]

    def _fc_state(self, pkt: bytes, now: float) -> None:
        for m in self._parse(pkt):
            if m.get_type() == "HEARTBEAT":
                self._fc_armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._fc_mode = px4.decode(m.custom_mode)
            elif m.get_type() == "LOCAL_POSITION_NED":
                vs = VehicleState(position_m=Vector3.from_array(frames.ned_to_enu(np.array([m.x, m.y, m.z]))),
                                  velocity_mps=Vector3.from_array(frames.ned_to_enu(np.array([m.vx, m.vy, m.vz]))),
                                  armed=self._fc_armed, flight_mode=self._fc_mode, connected=True)
                with self.lock:
                    self.fc_track.append((now, vs))
                    if len(self.fc_track) > 20000:
                        del self.fc_track[:10000]

    def fc_track_since(self, t: float) -> list[tuple[float, VehicleState]]:
        with self.lock:
            return [(ts, m) for ts, m in self.fc_track if ts >= t]

    def _check(self, pkt: bytes, now: float) -> None:
        for m in self._parse(pkt):
            if m.get_type() != "SET_POSITION_TARGET_LOCAL_NED":
                continue
            why = setpoint_problem(m, self.fence)
            with self.lock:
                self.setpoints_total += 1
                self.setpoints.append((now, m))
                if len(self.setpoints) > 30000:
                    del self.setpoints[:15000]
                if why:
                    self.unsafe.append((now, why))

    def setpoints_since(self, t: float) -> list:
        with self.lock:
            return [m for ts, m in self.setpoints if ts >= t]

    def unsafe_since(self, t: float) -> list[str]:
        with self.lock:
            return [why for ts, why in self.unsafe if ts >= t]

    def rate_hz(self, msgid: int, t0: float, t1: float) -> float:
        with self.lock:
            n = sum(1 for ts in self.stamps[msgid] if t0 <= ts < t1)
        return n / max(t1 - t0, 1e-6)

    def to_fc(self, msg) -> None:
        """Send one MAVLink message to the FC as the companion would (replies go to fmu)."""
        if self.sim_addr is None:
            raise RuntimeError("the FC has not sent anything yet")
        self.from_sim.sendto(msg.pack(self._enc), self.sim_addr)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.from_sim.close()
        self.to_fmu.close()


# ---------------------------------------------------------------- recording


class Recorder:
    """Every decoded message on some keys with the monotonic time it arrived: {name: [(t, msg)]}."""

    def __init__(self, session: zenoh.Session, keys: dict[str, tuple[str, type]]):
        self.lock = threading.Lock()
        self.data: dict[str, list[tuple[float, Any]]] = {name: [] for name in keys}
        self.subs = [session.declare_subscriber(key, self._cb(name, cls)) for name, (key, cls) in keys.items()]

    def _cb(self, name: str, cls: type):
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            with self.lock:
                self.data[name].append((time.monotonic(), msg))
        return on_sample

    def since(self, name: str, t: float = 0.0) -> list[tuple[float, Any]]:
        with self.lock:
            return [(ts, m) for ts, m in self.data[name] if ts >= t]

    def get(self, name: str, since: float = 0.0) -> list:
        """The messages (without times) that arrived at or after `since`."""
        with self.lock:
            return [m for ts, m in self.data[name] if ts >= since]

    def last(self, name: str):
        with self.lock:
            return self.data[name][-1][1] if self.data[name] else None

    def close(self) -> None:
        for s in self.subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be gone
                pass


def wait_until(pred: Callable[[], Any], timeout_s: float, interval_s: float = 0.05) -> Any:
    """pred()'s first truthy value within timeout_s, else None."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v or time.monotonic() >= deadline:
            return v
        time.sleep(interval_s)


# ---------------------------------------------------------------- the stack


class StackError(RuntimeError):
    """The stack did not come up (the message carries aero up's output and the service logs)."""


class SimStack:
    """`aero up --profile sim` on free ports, a MavlinkTap between sim and fmu, a client session.

    Ports: the router on a free TCP port; sim -> tap -> fmu on free UDP ports; gcs bound to a
    free UDP port (`gcs_port`; it sends to `gcs_remote_port`). Logs in `log_dir`.
    """

    def __init__(self, log_dir: str | Path | None = None, sensors: str = "none", speed: float = 1.0,
                 services: list[str] | None = None, extra_args: list[str] = (),
                 startup_timeout_s: float = 45.0):
        self.log_dir = Path(log_dir or tempfile.mkdtemp(prefix="aero-chaos-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.requested = services or profile_services("sim")
        self.sensors, self.speed, self.extra_args = sensors, speed, list(extra_args)
        self.services = fed_services(self.requested, sensors)[0]
        self.startup_timeout_s = startup_timeout_s
        self.fence = Geofence()
        self.session: zenoh.Session | None = None
        self.proc: subprocess.Popen | None = None
        self.tap: MavlinkTap | None = None
        self.starts = 0
        self.start()

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self.starts += 1
        self.services = fed_services(self.requested, self.sensors)[0]   # what `aero up` starts for them
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        sim_port, fmu_port, sim_bind = (free_port(socket.SOCK_DGRAM) for _ in range(3))
        self.gcs_port, self.gcs_remote_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
        self.fmu_port = fmu_port
        self.tap = MavlinkTap(sim_port, fmu_port, self.fence)
        run_dir = self.log_dir / f"run{self.starts}"
        run_dir.mkdir(parents=True, exist_ok=True)
        self.run_dir = run_dir
        argv = [sys.executable, "-m", "aeroperception.tools.cli", "up", "--profile", "sim",
                "--only", ",".join(self.services), "--listen", self.endpoint, "--log-dir", str(run_dir),
                "--sensors", self.sensors, "--speed", str(self.speed), "--fcu-url", f"udpin:127.0.0.1:{fmu_port}",
                "--arg", f"sim:--target=127.0.0.1:{sim_port}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
                "--arg", f"gcs:--param=local_port={self.gcs_port}",
                "--arg", f"gcs:--param=remote_port={self.gcs_remote_port}",
                "--arg", "gcs:--param=bind_ip=127.0.0.1", *self.extra_args]
        self._out_path = run_dir / "aero-up.out"
        with open(self._out_path, "wb") as out:
            # A private mission state dir: a stack never restores another run's mission.
            self.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env=dict(clean_env(), AERO_STATE_DIR=str(run_dir / "state")))
        try:
            self._wait_ready()
        except BaseException:
            self.stop()
            raise

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.startup_timeout_s
        while self.session is None:
            if self.proc.poll() is not None:
                raise StackError(f"`aero up` exited with code {self.proc.returncode}\n{self.describe()}")
            self.session = open_session(make_config(None, self.endpoint, mode="client"), max_wait_s=0.5)
            if time.monotonic() > deadline:
                raise StackError(f"router {self.endpoint} not reachable\n{self.describe()}")
        checks = [
            ("every service alive", lambda: all(self.alive(s) for s in self.services)),
            ("state/vehicle connected", lambda: self.latest("state/vehicle", VehicleState, 1.0, lambda m: m.connected)),
            ("planner setpoints through fmu", lambda: int(self.diag("fmu").values.get("setpoints_sent", 0)) > 100),
            ("mission/status", lambda: self.latest("mission/status", MissionStatus, 1.5)),
        ]
        for what, pred in checks:
            if not wait_until(pred, max(1.0, deadline - time.monotonic()), 0.2):
                raise StackError(f"stack not ready: {what} within {self.startup_timeout_s:.0f} s\n{self.describe()}")

    def restart(self) -> None:
        self.stop()
        self.start()

    def stop(self) -> None:
        stop_up(self.session, self.proc, self.pids())
        self.session = None
        if self.tap is not None:
            self.tap.close()
            self.tap = None

    def describe(self) -> str:
        parts = [f"--- aero up ({self._out_path}):\n{_tail(self._out_path)}"]
        for name in self.services:
            parts.append(f"--- {name}.log:\n{_tail(self.run_dir / f'{name}.log', 1500)}")
        return "\n".join(parts)

    # ------------------------------------------------------------ queries

    def pids(self) -> dict[str, int]:
        try:
            return json.loads((self.run_dir / "pids.json").read_text())
        except (OSError, ValueError, AttributeError):
            return {}

    def pid(self, name: str) -> int | None:
        pid = self.pids().get(name)
        return pid if pid is not None and is_service_process(pid, name) else None

    def alive(self, name: str, timeout_s: float = 1.0) -> bool:
        replies = self.session.liveliness().get(f"{LIVELINESS_ROOT}/default/{name}", timeout=timeout_s)
        return any(r.ok is not None for r in replies)

    def latest(self, key: str, cls: type, timeout_s: float = 3.0, pred: Callable[[Any], bool] | None = None):
        """The next message on `key` (matching pred) within timeout_s, else None."""
        got: list = []
        ev = threading.Event()

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            if not got and (pred is None or pred(msg)):
                got.append(msg)
                ev.set()

        sub = self.session.declare_subscriber(key, on_sample)
        try:
            ev.wait(timeout_s)
        finally:
            sub.undeclare()
        return got[0] if got else None

    def diag(self, name: str, timeout_s: float = 3.0) -> DiagnosticStatus:
        return self.latest(f"diagnostics/{name}", DiagnosticStatus, timeout_s) or DiagnosticStatus(name=name)

    def truth(self) -> VehicleState | None:
        return self.latest("sim/truth/state", VehicleState, 3.0)

    def mission_state(self) -> str:
        s = self.latest("mission/status", MissionStatus, 3.0)
        return s.state if s else "?"

    def call(self, key: str, request, reply_cls: type, timeout_s: float = 10.0):
        return call(self.session, key, request, reply_cls, timeout_s)

    def command(self, cmd: str, timeout_s: float = 15.0) -> Reply:
        try:
            return self.call("mission/srv/command", MissionCommand(command=cmd), Reply, timeout_s)
        except CallError as e:
            return Reply(success=False, message=str(e))

    def recorder(self, **keys: tuple[str, type]) -> Recorder:
        return Recorder(self.session, keys)

    def process_stats(self) -> dict[str, tuple[int, float]]:
        """{service: (rss_bytes, cpu_seconds)} of the running service processes, from /proc."""
        out = {}
        for name, pid in self.pids().items():
            stats = proc_stats(pid)
            if stats is not None and is_service_process(pid, name):
                out[name] = stats
        return out

    # ------------------------------------------------------------ flying

    def on_ground(self) -> bool:
        t = self.truth()
        return t is not None and t.position_m.z < 0.2 and not t.armed

    def ensure_ground(self, timeout_s: float = 60.0) -> bool:
        """Landed, disarmed, mission IDLE: LAND through the mission, else through fmu's LAND
        mode. False if that did not work (the caller restarts the stack)."""
        if self.on_ground() and self.mission_state() == "IDLE":
            return True
        if not self.on_ground():
            if not self.command("LAND").success:
                try:
                    self.call("fmu/srv/set_mode", SetModeRequest(mode="LAND"), SetModeReply, 8.0)
                except CallError:
                    pass
            wait_until(self.on_ground, timeout_s, 0.5)
        return bool(wait_until(lambda: self.on_ground() and self.mission_state() == "IDLE", 10.0, 0.5))

    def start_mission(self, mission_json: str, timeout_s: float = 40.0) -> str | None:
        """Load, TAKEOFF, START; None once EXECUTING, else why not."""
        try:
            r = self.call("mission/srv/load", LoadMissionRequest(mission_json=mission_json), LoadMissionReply, 10.0)
        except CallError as e:
            return f"load: {e}"
        if not r.success:
            return f"load refused: {r.message}"
        for cmd in ("TAKEOFF", "START"):
            r = self.command(cmd)
            if not r.success:
                return f"{cmd} refused: {r.message}"
        if not wait_until(lambda: self.mission_state() == "EXECUTING", timeout_s, 0.2):
            return f"mission not EXECUTING within {timeout_s:.0f} s (state {self.mission_state()})"
        return None


def _tail(path: Path, n: int = 3000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def proc_stats(pid: int) -> tuple[int, float] | None:
    """(resident set size in bytes, user+system CPU seconds) of one process, from /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        statm = Path(f"/proc/{pid}/statm").read_text().split()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()   # after "pid (comm) "
    cpu_s = (int(fields[11]) + int(fields[12])) / _CLK_TCK   # utime, stime
    return int(statm[1]) * _PAGE, cpu_s


# ---------------------------------------------------------------- judging


@dataclass
class RowResult:
    row: str
    injected: str
    expected: str
    observed: str = ""
    detect_s: float | None = None
    safe: bool | None = None
    safe_why: str = ""
    passed: bool = False
    fixed_by: str = ""
    duration_s: float = 0.0
    details: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return "PASS" if self.passed else "FAIL"


def judge_safety(track: list[tuple[float, VehicleState]], unsafe_setpoints: list[str], fence: Geofence,
                 mission_state: str) -> tuple[bool, str]:
    """Vehicle safe by the truth: no impact at speed, in the fence, no unsafe setpoint at the FC,
    and at the end holding (at rest in the air), landed and disarmed, or flying the mission."""
    if not track:
        return False, "no ground truth (sim gone?)"
    problems = []
    for _, m in track:
        p, v = m.position_m, m.velocity_mps
        speed = math.sqrt(v.x ** 2 + v.y ** 2 + v.z ** 2)
        if p.z < 0.1 and speed > IMPACT_SPEED_MPS:
            problems.append(f"ground impact at {speed:.1f} m/s")
            break
    worst = min(fence.distance_to_boundary_m(m.position_m.x, m.position_m.y, m.position_m.z) for _, m in track)
    if worst < 0:
        problems.append(f"left the geofence by {-worst:.1f} m")
    if unsafe_setpoints:
        problems.append(f"{len(unsafe_setpoints)} unsafe setpoints at the FC ({unsafe_setpoints[0]})")
    end = track[-1][1]
    speed = float(np.linalg.norm(end.velocity_mps.to_array()))
    if end.position_m.z < 0.2 and not end.armed:
        ending = "landed+disarmed"
    elif end.armed and end.position_m.z >= 0.2 and speed < AT_REST_MPS:
        ending = f"holding at {end.position_m.z:.1f} m"
    elif mission_state in ("EXECUTING", "LAND", "TAKEOFF") or end.flight_mode in ("LAND", "RTL"):
        ending = f"flying ({mission_state}, FC {end.flight_mode})"
    else:
        ending = ""
        problems.append(f"ends moving at {speed:.1f} m/s in {end.flight_mode} with mission {mission_state}")
    return (not problems), "; ".join(problems) or ending


def speed_of(m: VehicleState) -> float:
    return float(np.linalg.norm(m.velocity_mps.to_array()))


# ---------------------------------------------------------------- rows


@dataclass
class Ctx:
    """What a row's inject/observe steps share: the stack, a recorder, the injection time."""

    st: SimStack
    rec: Recorder
    t_inject: float = 0.0
    notes: dict = field(default_factory=dict)


@dataclass
class Row:
    name: str
    injected: str
    expected: str
    inject: Callable[[Ctx], None]
    observe: Callable[[Ctx], tuple[bool, str, float | None]]   # passed, observed, detect/react s
    airborne: bool = True          # inject mid-mission (else on the ground)
    cleanup: Callable[[Ctx], None] = lambda c: None
    breaks_stack: bool = False     # restart the stack afterwards
    prepare: Callable[[Ctx], None] = lambda c: None
    sensors: str = "none"          # the sim's --sensors this row needs (the stack restarts to change it)


def _kill(ctx: Ctx, name: str) -> None:
    pid = ctx.st.pid(name)
    if pid is None:
        raise RuntimeError(f"no running {name} process in pids.json")
    ctx.notes["old_pid"] = pid
    os.kill(pid, signal.SIGKILL)


def _restarted(ctx: Ctx, name: str, timeout_s: float = 20.0) -> float | None:
    """Seconds from the kill until a new `name` process holds the liveliness token, else None."""
    old = ctx.notes["old_pid"]
    ok = wait_until(lambda: ctx.st.pid(name) not in (None, old) and ctx.st.alive(name, 0.5), timeout_s, 0.1)
    return time.monotonic() - ctx.t_inject if ok else None


def _mission_states(ctx: Ctx, since: float) -> list[str]:
    seq = [m.state for _, m in ctx.rec.since("status", since)]
    return [s for i, s in enumerate(seq) if i == 0 or s != seq[i - 1]]


def _progressing(ctx: Ctx, window_s: float = 3.0) -> bool:
    """The mission is flying its waypoints: EXECUTING and the truth moving."""
    t0 = time.monotonic()
    time.sleep(window_s)
    truth = ctx.rec.since("truth", t0)
    st = ctx.rec.last("status")
    if st is None or st.state != "EXECUTING" or len(truth) < 2:
        return False
    return float(np.linalg.norm(truth[-1][1].position_m.to_array() - truth[0][1].position_m.to_array())) > 1.0


def _first_hold(ctx: Ctx, since: float) -> float | None:
    """Seconds from `since` to the first zero-velocity setpoint fmu sent: its brake (velocity
    only) or its position hold — fmu brakes to a stop first, then holds where it stopped."""
    with ctx.st.tap.lock:
        sps = [(t, m) for t, m in ctx.st.tap.setpoints if t >= since]
    for t, m in sps:
        if not m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE and m.vx == m.vy == m.vz == 0.0:
            return t - since
    return None


def kill_row(name: str) -> Row:
    def observe(ctx: Ctx):
        back = _restarted(ctx, name)
        if back is None:
            return False, f"{name} not restarted within 20 s", None
        if name == "mission":
            return _observe_mission_restart(ctx, back)
        if name in ("fmu", "planner"):
            return _observe_outage(ctx, name, back)
        flying = _progressing(ctx) or ctx.rec.last("status").state in ("LAND", "IDLE")
        states = _mission_states(ctx, ctx.t_inject)
        ok = flying and "HOLDING" not in states
        return ok, f"restarted in {back:.1f} s; mission {'->'.join(states)}{'' if flying else ', not progressing'}", back

    expected = {
        "fmu": "FC offboard-loss failsafe meanwhile; fmu restarted; then the vehicle holds until the mission "
               "re-checks it (mission HOLDING, survey not resumed by itself)",
        "planner": "fmu holds at once (liveliness); planner restarted; vehicle holds until the mission re-checks "
                   "(mission HOLDING), never EXECUTING with the vehicle frozen",
        "mission": "mission restarted, rebuilt from the vehicle (not IDLE in the air), accepts LAND; lands+disarms",
    }.get(name, "restarted by aero up; the mission flies on unaffected (no HOLD, no false link verdict)")
    return Row(f"kill_{name}", f"kill -9 {name}", expected, lambda c: _kill(c, name), observe)


def _held_after(ctx: Ctx, settle_s: float = 6.0, window_s: float = 2.0) -> tuple[bool, str]:
    """After an outage the mission must have held (HOLDING or LAND among its states since the
    injection) and the vehicle must not fly on in OFFBOARD while the mission says HOLDING.
    Ending EXECUTING again is allowed once it held: a resume by policy after the re-check."""
    time.sleep(settle_s)
    t_obs = time.monotonic()
    time.sleep(window_s)
    status = ctx.rec.last("status")
    truth = ctx.rec.since("truth", t_obs)
    moving = any(m.flight_mode == "OFFBOARD" and speed_of(m) > 0.5 for _, m in truth)
    states = _mission_states(ctx, ctx.t_inject)
    reacted = any(s in ("HOLDING", "LAND") for s in states)
    ok = status is not None and reacted and not (status.state == "HOLDING" and moving)
    fc_modes = sorted({m.flight_mode for _, m in ctx.rec.since("truth", ctx.t_inject)})
    return ok, (f"FC modes {','.join(fc_modes)}; mission {'->'.join(states)}; "
                f"{'moving in OFFBOARD' if moving else 'not flying on'} {settle_s + window_s:.0f} s after")


def _observe_outage(ctx: Ctx, name: str, back: float):
    """After fmu/planner came back: the vehicle must hold, the mission must not carry on by itself."""
    hold = _first_hold(ctx, ctx.t_inject) if name == "planner" else None
    ok, obs = _held_after(ctx)
    obs = f"restarted in {back:.1f} s; " + obs
    if hold is not None:
        obs = f"fmu hold after {hold:.2f} s; " + obs
    return ok, obs, hold if hold is not None else back


def _observe_mission_restart(ctx: Ctx, back: float):
    time.sleep(2.0)
    t = ctx.rec.last("truth")
    state = ctx.rec.last("status").state if ctx.rec.last("status") else "?"
    airborne = t is not None and t.position_m.z > 1.0
    r = ctx.st.command("LAND")
    landed = r.success and wait_until(ctx.st.on_ground, 40.0, 0.5)
    ok = airborne and state != "IDLE" and bool(landed)
    return ok, (f"restarted in {back:.1f} s as {state} at {t.position_m.z if t else float('nan'):.1f} m; "
                f"LAND {'accepted' if r.success else 'refused: ' + r.message[:60]}; "
                f"{'landed+disarmed' if landed else 'not landed'}"), back


def _router_kill(ctx: Ctx) -> None:
    """The router: its own process if aero up runs one as a child (<log-dir>/router.pid), else
    the `aero up` process that hosts it."""
    try:
        pid = int((ctx.st.run_dir / "router.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        pid = ctx.st.proc.pid
    ctx.notes["router_pid"] = pid
    ctx.notes["in_supervisor"] = pid == ctx.st.proc.pid
    os.kill(pid, signal.SIGKILL)


def _router_observe(ctx: Ctx):
    st = ctx.st
    others = [s for s in st.services]

    def reconnected() -> bool:
        s = open_session(make_config(None, st.endpoint, mode="client"), max_wait_s=0.5)
        if s is None:
            return False
        try:
            ok = all(any(r.ok is not None for r in s.liveliness().get(f"{LIVELINESS_ROOT}/default/{n}", timeout=0.5))
                     for n in others)
        finally:
            s.close()
        return ok

    back = wait_until(reconnected, 25.0, 0.5)
    react = time.monotonic() - ctx.t_inject if back else None
    where = "aero up (router inside it)" if ctx.notes["in_supervisor"] else "router process"
    if not back:
        return False, f"killed {where}; router/services not back within 25 s", None
    return True, f"killed {where}; router and every service back in {react:.1f} s", react


def _link_cut(ctx: Ctx) -> None:
    ctx.st.tap.cut.set()
    time.sleep(3.0)
    ctx.st.tap.cut.clear()
    ctx.notes["restored"] = time.monotonic()


def _link_observe(ctx: Ctx):
    t0 = ctx.t_inject
    lost = [t for t, m in ctx.rec.since("state", t0) if not m.connected]
    errs = [t for t, m in ctx.rec.since("fmu_diag", t0) if m.level >= DiagnosticStatus.ERROR]
    detect = min(lost[:1] + errs[:1]) - t0 if lost or errs else None
    held, obs = _held_after(ctx)
    ok = detect is not None and detect <= 0.6 and held
    return ok, (f"link lost reported after {detect:.2f} s" if detect is not None
                else "link loss never reported") + "; " + obs, detect


class FakeGcs:
    """A ground station on a UDP socket: MAV_TYPE_GCS heartbeats to gcs at 1 Hz until stopped."""

    def __init__(self, gcs_port: int, system_id: int = 255):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.target = ("127.0.0.1", gcs_port)
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER)
        self.stop_ev = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop_ev.is_set():
            hb = self.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            try:
                self.sock.sendto(hb.pack(self.mav), self.target)
                while select.select([self.sock], [], [], 0)[0]:
                    self.sock.recv(65535)   # telemetry from gcs: drain
            except OSError:
                pass
            self.stop_ev.wait(1.0)

    def stop(self) -> None:
        self.stop_ev.set()
        self.thread.join(2.0)
        self.sock.close()


def _gcs_prepare(ctx: Ctx) -> None:
    ctx.notes["gcs"] = FakeGcs(ctx.st.gcs_port)
    ok = ctx.st.latest("gcs/link", GcsLink, 8.0, lambda m: m.connected)
    ctx.notes["gcs_up"] = ok is not None


def _gcs_observe(ctx: Ctx):
    if not ctx.notes.get("gcs_up"):
        return False, "gcs/link never reported the fake ground station", None
    t0 = ctx.t_inject
    down = wait_until(lambda: [t for t, m in ctx.rec.since("gcs_link", t0) if not m.connected], 8.0, 0.05)
    hold = wait_until(lambda: [t for t, m in ctx.rec.since("status", t0) if m.state == "HOLDING"], 3.0, 0.05)
    time.sleep(4.0)  # braking into the hold
    states = _mission_states(ctx, t0)
    detect = down[0] - t0 if down else None
    ok = bool(down) and bool(hold)
    obs = (f"gcs/link down after {detect:.1f} s" if down else "gcs/link never down") + \
          f"; mission {'->'.join(states)}" + (f" (HOLD {hold[0] - t0:.1f} s after)" if hold else "")
    return ok, obs, (hold[0] - t0) if hold else detect


def _pause(name: str, seconds: float):
    def inject(ctx: Ctx) -> None:
        pid = ctx.st.pid(name)
        if pid is None:
            raise RuntimeError(f"no running {name} process")
        ctx.notes["paused_pid"] = pid
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            os.kill(pid, signal.SIGCONT)
        ctx.notes["resumed"] = time.monotonic()
    return inject


def _resume(ctx: Ctx) -> None:
    pid = ctx.notes.get("paused_pid")
    if pid:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass


def _hang_planner_observe(ctx: Ctx):
    t0 = ctx.t_inject
    hold = _first_hold(ctx, t0)
    track = [m for t, m in ctx.rec.since("truth", t0) if t <= ctx.notes["resumed"]]
    if len(track) < 10:
        return False, "no truth during the hang", hold
    p = np.array([m.position_m.to_array() for m in track])
    v0 = track[0].velocity_mps.to_array()
    d = v0 / (np.linalg.norm(v0) or 1.0)
    along = (p - p[0]) @ d
    overshoot, flyback = float(along.max()), float(along.max() - along[-1])
    rest = speed_of(track[-1]) < AT_REST_MPS
    back = wait_until(lambda: "streaming" in ctx.st.diag("fmu").values.get("planner", ""), 5.0, 0.2)
    ok = hold is not None and hold <= 0.4 and rest and flyback < 0.3 and bool(back)
    obs = (f"fmu hold after {hold:.2f} s" if hold is not None else "no hold setpoint") + \
          (f"; stopped {overshoot:.2f} m on, flew back {flyback:.2f} m; "
           f"{'at rest' if rest else f'{speed_of(track[-1]):.1f} m/s'} at SIGCONT; "
           f"planner {'streaming again' if back else 'not back'}")
    return ok, obs, hold


def _hang_fmu_observe(ctx: Ctx):
    t0 = ctx.t_inject
    fs = [t for t, m in ctx.rec.since("truth", t0) if m.flight_mode != "OFFBOARD"]
    react = fs[0] - t0 if fs else None
    return _after_fc_failsafe(ctx, react, "FC failsafe")


def _after_fc_failsafe(ctx: Ctx, react: float | None, what: str):
    held, obs = _held_after(ctx)
    ok = react is not None and react <= 1.5 and held
    return ok, (f"{what} after {react:.2f} s" if react is not None else f"no {what}") + "; " + obs, react


def _clock_jump(ctx: Ctx) -> None:
    """Rogue sim/clock ticks 1 h ahead for 1 s, then 1 h behind for 1 s (100 Hz each)."""
    pub = ctx.st.session.declare_publisher("sim/clock", encoding=encoding_for(Clock))
    try:
        for offset_s in (3600.0, -3600.0):
            for _ in range(100):
                pub.put(encode(Clock(header=Header(stamp_ns=time.time_ns() + int(offset_s * 1e9)), speed_factor=1.0)))
                time.sleep(0.01)
    finally:
        pub.undeclare()


def _clock_observe(ctx: Ctx):
    t0 = ctx.t_inject
    holds0 = ctx.notes.get("holds0", 0)
    stamps = [t for t, _ in ctx.rec.since("state", t0)]
    gaps = np.diff(stamps) if len(stamps) > 1 else np.array([math.inf])
    progressing = _progressing(ctx, 2.0) or ctx.rec.last("status").state in ("LAND", "IDLE")
    holds = int(ctx.st.diag("fmu").values.get("holds_sent", 0)) - holds0
    ok = progressing and float(gaps.max()) < 0.2 and holds <= 0
    return ok, (f"state/vehicle max gap {gaps.max() * 1e3:.0f} ms; fmu holds +{holds}; mission "
                f"{'->'.join(_mission_states(ctx, t0))}{'' if progressing else ', not progressing'}"), None


def _clock_prepare(ctx: Ctx) -> None:
    ctx.notes["holds0"] = int(ctx.st.diag("fmu").values.get("holds_sent", 0))


def _reboot(ctx: Ctx) -> None:
    """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN to the FC, then PX4's default stream rates (the sim keeps
    its rates across a reboot; real PX4 comes back with LOCAL_POSITION_NED at 30 Hz, HIGHRES_IMU 50)."""
    tap, enc = ctx.st.tap, ctx.st.tap._enc
    ctx.notes["rate_before"] = tap.rate_hz(LOCAL_POSITION_NED, time.monotonic() - 3.0, time.monotonic())
    tap.to_fc(enc.command_long_encode(1, 1, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0))
    time.sleep(0.2)
    for mid, hz in ((LOCAL_POSITION_NED, 30.0), (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 30.0),
                    (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 50.0)):
        tap.to_fc(enc.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid, 1e6 / hz, 0, 0, 0, 0, 0))


def _reboot_observe(ctx: Ctx):
    t0 = ctx.t_inject
    tap = ctx.st.tap
    rebooted = wait_until(lambda: [a for a in tap.acks if a[0] >= t0 and a[1] == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
                                   and a[2] == mavlink.MAV_RESULT_ACCEPTED], 5.0, 0.1)
    back = wait_until(lambda: tap.rate_hz(LOCAL_POSITION_NED, time.monotonic() - 1.0, time.monotonic()) >= 45.0
                      and time.monotonic() - t0 > 1.5, 10.0, 0.1)
    react = time.monotonic() - t0 if back else None
    t1 = time.monotonic()
    time.sleep(3.0)
    n_state = len(ctx.rec.since("state", t1)) / 3.0
    n_imu = len(ctx.rec.since("imu", t1)) / 3.0
    ok = bool(rebooted) and n_state >= 45.0 and n_imu >= 90.0
    obs = (f"{'rebooted' if rebooted else 'no reboot seen'}; state/vehicle {ctx.notes['rate_before']:.0f} -> "
           f"{n_state:.0f} Hz, fmu/out/sensor_combined {n_imu:.0f} Hz after")
    return ok, obs, react


def _lidar_observe(ctx: Ctx):
    """kill -9 lidar mid-flight: the costmap stops; the planner must not fly on blind. It holds
    (zero horizontal velocity at the FC, planner/status stale_costmap) within costmap_timeout_s,
    and once aero up has restarted lidar and a fresh costmap arrives the mission flies on."""
    t0 = ctx.t_inject
    stale = wait_until(lambda: next((t for t, m in ctx.rec.since("planner", t0) if m.obstacle_state == "stale_costmap"),
                                    None), 5.0)
    back = _restarted(ctx, "lidar", 30.0)
    with ctx.st.tap.lock:
        sps = [(t, m) for t, m in ctx.st.tap.setpoints if t >= t0]
    hold = next((t - t0 for t, m in sps if not m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
                 and m.vx == 0.0 and m.vy == 0.0), None)
    if back is None:
        return False, "lidar not restarted within 30 s", hold
    fresh = wait_until(lambda: any(t > t0 + back and m.obstacle_state != "stale_costmap"
                                   for t, m in ctx.rec.since("planner", t0)), 20.0)
    flying = _progressing(ctx) or ctx.rec.last("status").state in ("LAND", "IDLE")
    states = _mission_states(ctx, t0)
    # While lidar was down, the vehicle slowed to a stop or was stopping (not cruising on).
    down = [m for t, m in ctx.rec.since("truth", t0 + (stale - t0 if stale else 0) + 2.0) if t < t0 + back]
    cruising = any(speed_of(m) > 1.0 for m in down)
    ok = bool(stale and hold is not None and hold < 1.0 and fresh and flying and not cruising)
    detail = (f"planner stale_costmap after {stale - t0:.2f} s, " if stale else "no stale_costmap verdict, ") + \
        (f"FC zero horizontal velocity after {hold:.2f} s; " if hold is not None else "never a zero-velocity setpoint; ")
    return ok, (detail + f"lidar restarted in {back:.1f} s; costmap {'fresh again' if fresh else 'NOT back'}; "
                f"{'cruised on blind; ' if cruising else ''}mission {'->'.join(states)}"
                f"{'' if flying else ', not progressing'}"), hold


def _safety_row_if_present(services: list[str]) -> list[str]:
    return [s for s in ("fmu", "planner", "mission", "gcs", "diagnostics", "safety") if s in services]


def build_rows(services: list[str]) -> dict[str, Row]:
    rows = [kill_row(s) for s in _safety_row_if_present(services)]
    rows += [
        Row("router_kill", "kill -9 the Zenoh router",
            "supervisor detects it and restarts the router; every service reconnects; vehicle holds meanwhile",
            _router_kill, _router_observe, breaks_stack=True),
        Row("fc_link_loss", "FC MAVLink cut both ways for 3 s",
            "state/vehicle connected=false or diagnostics/fmu ERROR within 0.5 s; FC offboard-loss failsafe; "
            "mission HOLDING after, no resumption by itself",
            _link_cut, _link_observe, cleanup=lambda c: c.st.tap.cut.clear()),
        Row("gcs_loss", "MAV_TYPE_GCS heartbeats to gcs, then silence",
            "gcs/link connected=false after gcs_timeout_s (3.5 s); mission HOLDING (link-loss policy)",
            lambda c: c.notes["gcs"].stop(), _gcs_observe, prepare=_gcs_prepare,
            cleanup=lambda c: c.notes.get("gcs") and c.notes["gcs"].stop()),
        Row("hang_planner", "SIGSTOP planner 3 s, SIGCONT",
            "fmu brakes within 0.4 s (setpoint_timeout_s 0.3 + a tick), stops without flying back; "
            "planner streams again after SIGCONT",
            _pause("planner", 3.0), _hang_planner_observe, cleanup=_resume),
        Row("hang_fmu", "SIGSTOP fmu 3 s, SIGCONT",
            "FC offboard-loss failsafe within 1.5 s; after SIGCONT the vehicle holds until the mission "
            "re-checks (mission HOLDING), never flies on in OFFBOARD by itself",
            _pause("fmu", 3.0), _hang_fmu_observe, cleanup=_resume),
        Row("clock_jump", "rogue sim/clock +1 h then -1 h (1 s each)",
            "no decision changes: timeouts run on monotonic clocks; state/vehicle gaps < 200 ms; no fmu hold; "
            "mission flies on",
            _clock_jump, _clock_observe, prepare=_clock_prepare),
        Row("fc_reboot", "FC reboot on the ground (PX4 default rates after)",
            "fmu detects the reboot and re-requests its rates: state/vehicle >= 45 Hz, IMU >= 90 Hz",
            _reboot, _reboot_observe, airborne=False),
    ]
    if "lidar" in services:   # last: it needs a stack rendering the LiDAR (a restart to switch)
        rows.append(Row("kill_lidar", "kill -9 lidar mid-flight (LiDAR rendered)",
                        "planner holds within costmap_timeout_s (0.5 s) + a tick: stale_costmap, zero horizontal "
                        "velocity at the FC, never flies on blind; lidar restarted; the mission flies on once "
                        "the costmap is fresh",
                        lambda c: _kill(c, "lidar"), _lidar_observe, sensors="lidar"))
    return {r.name: r for r in rows}


# ---------------------------------------------------------------- running


RECORDED = dict(truth=("sim/truth/state", VehicleState), status=("mission/status", MissionStatus),
                state=("state/vehicle", VehicleState), fmu_diag=("diagnostics/fmu", DiagnosticStatus),
                gcs_link=("gcs/link", GcsLink), imu=("fmu/out/sensor_combined", Imu),
                planner=("planner/status", TrajectoryStatus))


def run_row(st: SimStack, row: Row, mission_json: str, inject_after_s: float = 2.5) -> RowResult:
    """Fly, inject, observe, judge. Leaves the stack on the ground (restarted if it had to be)."""
    res = RowResult(row.name, row.injected, row.expected, fixed_by=EXPECTED_FIXED_BY.get(row.name, ""))
    t_start = time.monotonic()
    if st.sensors != row.sensors:
        st.sensors = row.sensors
        st.restart()
    elif not st.ensure_ground():
        st.restart()
    rec = st.recorder(**RECORDED)
    ctx = Ctx(st, rec)
    t_unsafe = time.monotonic()
    try:
        row.prepare(ctx)
        if row.airborne:
            why = st.start_mission(mission_json)
            if why:   # a previous row may have left the stack odd: once more on a fresh one
                st.restart()
                why = st.start_mission(mission_json)
            if why:
                res.observed = f"could not start the mission: {why}"
                return res
            time.sleep(inject_after_s)
        ctx.t_inject = time.monotonic()
        row.inject(ctx)
        res.passed, res.observed, res.detect_s = row.observe(ctx)
    except Exception as e:  # noqa: BLE001 - one broken row must not stop the table
        res.observed = f"harness error: {type(e).__name__}: {e}"
        res.passed = False
    finally:
        try:
            row.cleanup(ctx)
        except Exception:  # noqa: BLE001
            pass
        t_from = ctx.t_inject or t_unsafe
        track = rec.since("truth", t_from)
        if st.tap and (not track or track[-1][0] < time.monotonic() - 2.0):   # Zenoh gone: the FC's view
            track = st.tap.fc_track_since(t_from)
            res.details["safety_from"] = "FC LOCAL_POSITION_NED (no ground truth over Zenoh)"
        status = rec.last("status")
        res.safe, res.safe_why = judge_safety(track, st.tap.unsafe_since(t_unsafe) if st.tap else [], st.fence,
                                              status.state if status else "?")
        if "safety_from" in res.details:
            res.safe_why += " (by the FC's own position: no Zenoh)"
        rec.close()
    res.passed = bool(res.passed and res.safe)
    # A failed row leaves the stack in whatever state the fault made (a restarted service that lost
    # its state, a FC in LAND): the next row starts on a fresh stack.
    if row.breaks_stack or not res.passed or not st.ensure_ground():
        st.restart()
    res.duration_s = time.monotonic() - t_start
    return res


def format_table(results: list[RowResult]) -> str:
    head = ["row", "injected", "expected outcome", "observed", "detect/react s", "vehicle safe (truth)", "result"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        det = f"{r.detect_s:.2f}" if r.detect_s is not None else "-"
        safe = ("yes" if r.safe else "NO") + (f": {r.safe_why}" if r.safe_why else "")
        verdict = r.verdict + (f" (needs {r.fixed_by})" if not r.passed and r.fixed_by else "")
        lines.append("| " + " | ".join([r.row, r.injected, r.expected, r.observed, det, safe, verdict]) + " |")
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("chaos", help="inject faults into a sim stack mid-mission, print a figures table")
    p.add_argument("--rows", default="", help="comma-separated rows (default: all); `--list` shows them")
    p.add_argument("--list", action="store_true", help="list the rows and their expected outcomes")
    p.add_argument("--json", default=None, metavar="FILE", help="write the results as JSON too")
    p.add_argument("--mission", default=str(DEFAULT_MISSION), help="mission file flown in each row")
    p.add_argument("--log-dir", default=None, help="stack logs (default a new temporary directory)")
    p.set_defaults(func=run)


def run(args) -> int:
    services = profile_services("sim")
    rows = build_rows(services)
    if args.list:
        for r in rows.values():
            print(f"{r.name:<16} {r.injected}\n{'':<16} expected: {r.expected}")
        return 0
    names = [s.strip() for s in args.rows.split(",") if s.strip()] or list(rows)
    unknown = [n for n in names if n not in rows]
    if unknown:
        raise CliError(f"unknown row {', '.join(unknown)}; rows: {', '.join(rows)}")
    try:
        mission_json = Path(args.mission).read_text()
    except OSError as e:
        raise CliError(f"cannot read mission {args.mission}: {e.strerror}") from None
    print(f"aero chaos: {len(names)} rows on the sim profile ({', '.join(services)})", flush=True)
    try:
        st = SimStack(args.log_dir, sensors=rows[names[0]].sensors)
    except StackError as e:
        raise CliError(f"the sim stack did not come up: {str(e).splitlines()[0]}") from None
    print(f"stack up (router {st.endpoint}, logs {st.log_dir})", flush=True)
    results: list[RowResult] = []
    try:
        for name in names:
            res = run_row(st, rows[name], mission_json)
            results.append(res)
            print(f"  {res.row:<16} {res.verdict}  {res.observed}  [safe: {res.safe_why}] ({res.duration_s:.0f} s)",
                  flush=True)
    finally:
        st.stop()
    print()
    print(format_table(results))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) | {"verdict": r.verdict} for r in results], indent=1) + "\n")
    pending = [r.row for r in results if not r.passed and r.fixed_by]
    unexpected = [r.row for r in results if not r.passed and not r.fixed_by]
    print(f"\n{sum(r.passed for r in results)}/{len(results)} rows pass; failing pending another branch's fix: "
          f"{', '.join(pending) or 'none'}; unexpected failures: {', '.join(unexpected) or 'none'}")
    return 1 if unexpected else 0
