"""gcs as a process next to real ground-station traffic: who counts
as a ground station, gcs restarts and stalls, a second listen-only station, the vehicle profile's
identity beside a real PX4's heartbeat, and safety/status forwarded to ground stations.

gcs runs alone (python -m aeroperception.services.gcs) on an in-process Zenoh router; ground
stations are pymavlink sockets (and MAVSDK for the listen-only one). Loopback only, free ports."""
from __future__ import annotations

import asyncio
import importlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aeroperception.schemas import DiagnosticStatus, GcsLink, SafetyStatus, VehicleStatus  # noqa: E402
from aeroperception.services.gcs.link import Parser, make_mav  # noqa: E402
from aerotest import clean_env, free_udp_port, stop_up, wait_for_message, wait_until  # noqa: E402


class GcsProcess:
    """One gcs service process (started and stopped by handle)."""

    def __init__(self, router: str, log: Path, local_port: int, remote_port: int, *params: str):
        self.router, self.log_path, self.args = router, log, [
            sys.executable, "-m", "aeroperception.services.gcs", "--connect", router,
            "--local-port", str(local_port), "--remote-port", str(remote_port), "--bind-ip", "127.0.0.1",
            *[a for p in params for a in ("--param", p)]]
        self.proc: subprocess.Popen | None = None
        self.started_s = 0.0

    def start(self) -> "GcsProcess":
        self.log = open(self.log_path, "a")
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(self.args, env=clean_env(), stdout=subprocess.DEVNULL, stderr=self.log,
                                     stdin=subprocess.DEVNULL)
        return self

    def stop(self) -> None:
        if self.proc is not None:
            stop_up(None, self.proc, {})          # SIGINT, bounded wait, then kill
            self.proc = None
        self.log.close()


class Station:
    """A pymavlink ground station socket: heartbeats (MAV_TYPE_GCS unless told) in a thread, and
    everything received, decoded."""

    def __init__(self, gcs_port: int, system_id: int = 255, component_id: int = 190, bind_port: int = 0,
                 mav_type: int = M.MAV_TYPE_GCS, autopilot: int = M.MAV_AUTOPILOT_INVALID):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", bind_port))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.dest = ("127.0.0.1", gcs_port)
        self.mav = make_mav(system_id, component_id)
        self.mav_type, self.autopilot = mav_type, autopilot
        self.parser = Parser()
        self.lock = threading.Lock()
        self.rx: list[tuple[float, object]] = []
        self.beating = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), self.dest)

    def heartbeat(self) -> None:
        self.send(M.MAVLink_heartbeat_message(self.mav_type, self.autopilot, 0, 0, M.MAV_STATE_ACTIVE, 3))

    def _run(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            if self.beating.is_set() and time.monotonic() - last >= 0.5:
                self.heartbeat()
                last = time.monotonic()
            try:
                data, _ = self.sock.recvfrom(65535)
            except (socket.timeout, OSError):
                continue
            now = time.monotonic()
            with self.lock:
                self.rx += [(now, m) for m in self.parser.feed(data)]

    def messages(self, mtype: str | None = None, since: float = 0.0) -> list:
        with self.lock:
            return [m for t, m in self.rx if t >= since and (mtype is None or m.get_type() == mtype)]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


class Links:
    """Every gcs/link message with its arrival time."""

    def __init__(self, node):
        self.lock = threading.Lock()
        self.got: list[tuple[float, GcsLink]] = []
        node.subscribe("gcs/link", GcsLink, self._on)

    def _on(self, m: GcsLink) -> None:
        with self.lock:
            self.got.append((time.monotonic(), m))

    def since(self, t: float) -> list[tuple[float, GcsLink]]:
        with self.lock:
            return [(s, m) for s, m in self.got if s >= t]


def test_only_ground_stations_count_restart_and_stall_give_no_false_loss(zenoh_router, make_node, tmp_path):
    """Issue 8 #4: a stray vehicle heartbeat is not a ground station; a restarted gcs says nothing
    on gcs/link before it has listened for gcs_timeout_s (so a connected station is no "loss");
    a 5 s SIGSTOP (timeout 2 s) while the station keeps beating is no loss either; a station that
    really goes away is lost after the timeout."""
    node = make_node("test-gcs-link")
    links = Links(node)
    port = free_udp_port()
    gcs = GcsProcess(zenoh_router, tmp_path / "gcs.log", port, free_udp_port(), "gcs_timeout_s=2.0").start()
    stray = Station(port, system_id=42, component_id=1, mav_type=M.MAV_TYPE_QUADROTOR, autopilot=M.MAV_AUTOPILOT_PX4)
    station = Station(port)
    try:
        # a stray heartbeat (a vehicle, not a ground station): no verdict for the timeout, then "none"
        t0 = gcs.started_s
        deadline = time.monotonic() + 8
        while not links.since(t0) and time.monotonic() < deadline:
            stray.heartbeat()
            time.sleep(0.3)
        first_t, first = links.since(t0)[0]
        assert first.connected is False and first_t - t0 >= 2.0, (first_t - t0, first)
        assert not any(m.connected for _, m in links.since(t0))
        diag = wait_for_message(node.session, "diagnostics/gcs", DiagnosticStatus,
                                lambda d: int(d.values.get("ignored[heartbeat_not_gcs]", 0)) >= 1, timeout_s=5)
        assert diag.values["ground_stations"] == "0"

        # a real ground station: up
        station.beating.set()
        wait_until(lambda: any(m.connected for _, m in links.since(t0)), 5, "gcs/link connected")

        # gcs restarts while the station beats: it never says "not connected"
        gcs.stop()
        t_restart = time.monotonic()
        gcs.start()
        wait_until(lambda: any(m.connected for _, m in links.since(t_restart)), 10, "gcs/link connected again")
        time.sleep(1.0)
        assert all(m.connected for _, m in links.since(t_restart)), links.since(t_restart)

        # gcs stopped for 5 s (> timeout) while the station beats on: no loss after the resume
        os.kill(gcs.proc.pid, signal.SIGSTOP)
        time.sleep(5.0)
        t_resume = time.monotonic()
        os.kill(gcs.proc.pid, signal.SIGCONT)
        time.sleep(3.0)
        after = links.since(t_resume)
        assert after and all(m.connected for _, m in after), after
        diag = wait_for_message(node.session, "diagnostics/gcs", DiagnosticStatus,
                                lambda d: int(d.values.get("stalls", 0)) >= 1, timeout_s=5)

        # the station really goes: lost after about the timeout
        station.beating.clear()
        t_gone = time.monotonic()
        wait_until(lambda: any(not m.connected for _, m in links.since(t_gone)), 6, "gcs/link lost")
        lost_t = next(t for t, m in links.since(t_gone) if not m.connected)
        assert 1.5 <= lost_t - t_gone <= 4.0, lost_t - t_gone
    finally:
        if gcs.proc is not None and gcs.proc.poll() is None:
            os.kill(gcs.proc.pid, signal.SIGCONT)
        gcs.stop()
        stray.close()
        station.close()


def test_a_second_listen_only_station_connects_while_another_talks(zenoh_router, make_node, tmp_path):
    """Issue 9 #4: station A talks to gcs (heartbeats); MAVSDK listens on the default destination
    (remote_port) without ever sending first, and still finds the autopilot."""
    pytest.importorskip("mavsdk.asyncio")
    port, listen_port = free_udp_port(), free_udp_port()
    gcs = GcsProcess(zenoh_router, tmp_path / "gcs.log", port, listen_port).start()
    a = Station(port)
    a.beating.set()
    try:
        wait_until(lambda: a.messages("HEARTBEAT"), 10, "gcs heartbeats at the talking station")

        async def listen_only():
            mavsdk = importlib.import_module("mavsdk.asyncio")
            config = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
            async with mavsdk.Mavsdk(config) as sdk:
                await sdk.add_any_connection(f"udpin://127.0.0.1:{listen_port}")
                system = await sdk.first_autopilot(timeout_s=10.0)
                return system is not None

        assert asyncio.run(asyncio.wait_for(listen_only(), 30)), "MAVSDK on the default port saw no autopilot"
        t = time.monotonic()
        time.sleep(1.5)
        assert a.messages("HEARTBEAT", since=t), "the talking station kept its telemetry"
    finally:
        gcs.stop()
        a.close()


def test_vehicle_profile_one_vehicle_beside_the_flight_controller(zenoh_router, make_node, tmp_path):
    """Issue 9 #6: with identity=companion, gcs is component 191 (onboard computer) of the flight
    controller's system (learned from fmu/out/vehicle_status), not a second vehicle: a listener on
    the ground-station port, fed by a PX4-like heartbeat (sys 7 comp 1, quadrotor) and gcs, sees
    exactly one vehicle."""
    node = make_node("test-fc")
    pub = node.publisher("fmu/out/vehicle_status", VehicleStatus)
    listener = Station(free_udp_port())              # the ground station: listens only
    fc = Station(listener.port, system_id=7, component_id=1, mav_type=M.MAV_TYPE_QUADROTOR,
                 autopilot=M.MAV_AUTOPILOT_PX4)       # PX4's own GCS link, to the same port
    gcs = GcsProcess(zenoh_router, tmp_path / "gcs.log", free_udp_port(), listener.port, "identity=companion").start()
    try:
        stop = threading.Event()

        def feed():
            while not stop.is_set():
                pub.publish(VehicleStatus(nav_state="HOLD", system_id=7, autopilot="px4"))
                fc.heartbeat()
                time.sleep(0.3)
        threading.Thread(target=feed, daemon=True).start()
        wait_until(lambda: any(m.get_srcSystem() == 7 and m.get_srcComponent() == 191
                               for m in listener.messages("HEARTBEAT")), 15, "gcs heartbeat as 7:191")
        t = time.monotonic()
        time.sleep(3.0)
        stop.set()
        beats = listener.messages("HEARTBEAT", since=t)
        who = {(m.get_srcSystem(), m.get_srcComponent()): m.type for m in beats}
        vehicles = [k for k, typ in who.items() if typ not in (M.MAV_TYPE_GCS, M.MAV_TYPE_ONBOARD_CONTROLLER)]
        assert vehicles == [(7, 1)], who                       # one vehicle: the flight controller
        assert who[(7, 191)] == M.MAV_TYPE_ONBOARD_CONTROLLER
        ours = [m for m in beats if m.get_srcComponent() == 191]
        assert all(m.autopilot == M.MAV_AUTOPILOT_INVALID for m in ours)
        # and no vehicle telemetry from the companion (the FC sends its own)
        assert not [m for m in listener.messages(since=t) if m.get_srcComponent() == 191
                    and m.get_type() in ("GLOBAL_POSITION_INT", "ATTITUDE", "SYS_STATUS", "MISSION_CURRENT")]
    finally:
        gcs.stop()
        listener.close()
        fc.close()


def test_safety_status_reaches_ground_stations(zenoh_router, make_node, tmp_path):
    """Issue 9 #8: SYS_STATUS reports the geofence honestly (not present without safety/status;
    present, enabled, healthy from its geofence_status), and safety's warnings/errors arrive as
    STATUSTEXT once per change, errors at a higher severity than warnings."""
    node = make_node("test-safety")
    pub = node.publisher("safety/status", SafetyStatus)
    port = free_udp_port()
    gcs = GcsProcess(zenoh_router, tmp_path / "gcs.log", port, free_udp_port()).start()
    st = Station(port)
    st.beating.set()
    fence = M.MAV_SYS_STATUS_GEOFENCE
    try:
        wait_until(lambda: st.messages("SYS_STATUS"), 10, "SYS_STATUS")
        s = st.messages("SYS_STATUS")[-1]
        assert not s.onboard_control_sensors_present & fence          # no safety service: no fence

        def publish_for(status: SafetyStatus, seconds: float) -> float:
            t = time.monotonic()
            while time.monotonic() - t < seconds:
                pub.publish(status)
                time.sleep(0.2)
            return t

        t = publish_for(SafetyStatus(geofence_status=SafetyStatus.GEOFENCE_OK, distance_to_geofence_m=80.0), 2.0)
        s = [m for m in st.messages("SYS_STATUS", since=t + 1.0)][-1]
        assert s.onboard_control_sensors_present & fence and s.onboard_control_sensors_enabled & fence
        assert s.onboard_control_sensors_health & fence                 # no breach: healthy
        t = publish_for(SafetyStatus(geofence_status=SafetyStatus.GEOFENCE_VIOLATION, distance_to_geofence_m=-3.0,
                                     safety_level=SafetyStatus.LEVEL_CAUTION,
                                     active_warnings=["battery low (28%)"],
                                     active_errors=["geofence breached (3.0 m outside)"]), 2.0)
        s = [m for m in st.messages("SYS_STATUS", since=t + 1.0)][-1]
        assert s.onboard_control_sensors_present & fence and not s.onboard_control_sensors_health & fence
        texts = [(m.severity, m.text) for m in st.messages("STATUSTEXT", since=t)]
        assert texts.count((M.MAV_SEVERITY_WARNING, "Safety: battery low (28%)")) == 1, texts   # once per change
        assert texts.count((M.MAV_SEVERITY_CRITICAL, "Safety: geofence breached (3.0 m outside)")) == 1, texts
    finally:
        gcs.stop()
        st.close()
