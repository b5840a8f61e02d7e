"""gcs against a real stack (sim + fmu + planner + mission + gcs over Zenoh), driven by real
ground-station software: pymavlink first, then MAVSDK-Python. Loopback only, free ports."""
from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import importlib
import importlib.util
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aeroperception.schemas import DiagnosticStatus, GcsLink, HomePosition, MissionStatus  # noqa: E402
from aeroperception.services.gcs.contract import (  # noqa: E402
    DEFAULT_HOME_ALT_M, DEFAULT_HOME_LAT_DEG, DEFAULT_HOME_LON_DEG,
)
from aeroperception.services.gcs.messages import extension_fields  # noqa: E402
from aeroperception.services.gcs.home import Home  # noqa: E402
from aeroperception.services.sim.vehicle.params import make_params  # noqa: E402
from aerotest import Capture, free_udp_port, wait_for_message, wait_until  # noqa: E402

# The flight controller's home: the built-in sim's (PX4 SITL's default, near Zurich), which gcs
# takes from fmu/out/home_position. gcs's own home parameters (Tokyo) are only the fallback.
_SIM = make_params()
HOME = Home(_SIM.SIM_HOME_LAT, _SIM.SIM_HOME_LON, _SIM.SIM_HOME_ALT)
PARAM_HOME = Home(DEFAULT_HOME_LAT_DEG, DEFAULT_HOME_LON_DEG, DEFAULT_HOME_ALT_M)


def start_stack(stack, gcs_port: int, gcs_remote: int):
    """The stack, once gcs converts about the flight controller's home (fmu/out/home_position),
    so missions uploaded by the tests are converted about the sim's home."""
    p1, p2 = free_udp_port(), free_udp_port()
    st = stack(["sim", "fmu", "planner", "mission", "gcs"], extra_args=[
        "--arg", f"fmu:--fcu-url=udpin:127.0.0.1:{p1}", "--arg", f"sim:--target=127.0.0.1:{p1}",
        "--arg", f"sim:--bind=127.0.0.1:{p2}", "--arg", "sim:--sensors=none",
        "--arg", f"gcs:--local-port={gcs_port}", "--arg", f"gcs:--remote-port={gcs_remote}",
        "--arg", "gcs:--bind-ip=127.0.0.1"], timeout_s=40)
    wait_for_message(st.session, "diagnostics/gcs", DiagnosticStatus,
                     lambda d: d.values.get("home_source") == "flight_controller", timeout_s=15)
    return st


class Gcs:
    """A pymavlink ground station that talks first (gcs learns our address)."""

    def __init__(self, gcs_port: int, system_id: int = 255):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=system_id,
                                               source_component=190, dialect="common")
        self.log: list = []

    def heartbeat(self):
        self.conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def recv(self, mtype, pred=lambda m: True, timeout_s=5.0):
        deadline = time.monotonic() + timeout_s
        last_hb = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() - last_hb > 1.0:
                self.heartbeat()
                last_hb = time.monotonic()
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None and m.get_type() == mtype and pred(m):
                return m
        raise AssertionError(f"no {mtype} within {timeout_s} s")

    def close(self):
        self.conn.close()


@contextlib.asynccontextmanager
async def mavsdk_autopilot(port: int):
    """MAVSDK (in-process) as a ground station on udpin://127.0.0.1:port, yielding the autopilot."""
    mavsdk = importlib.import_module("mavsdk.asyncio")
    config = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    async with mavsdk.Mavsdk(config) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await sdk.first_autopilot(timeout_s=15.0)
        assert system is not None, "MAVSDK saw no autopilot"
        yield system

def waypoints(n=4, alt=5.0):
    pts = []
    for i in range(n):
        north, east = (4, 4, 0, 0)[i % 4], (0, 4, 4, 0)[i % 4]
        lat, lon = HOME.projection.reproject(north, east)
        pts.append((lat, lon, alt))
    return pts


def test_pymavlink_ground_station(stack):
    port = free_udp_port()
    st = start_stack(stack, port, free_udp_port())
    g = Gcs(port)
    try:
        g.heartbeat()
        hb = g.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout_s=10)
        assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
        link = wait_for_message(st.session, "gcs/link", GcsLink, lambda m: m.connected, timeout_s=5)
        assert link.system_id == 255

        # telemetry from the stack's state, geodetic about the flight controller's home (fmu reads the
        # sim's HOME_POSITION), not gcs's parameter default: the vehicle sits at home
        fc_home = wait_for_message(st.session, "fmu/out/home_position", HomePosition, timeout_s=5)
        assert (fc_home.latitude_deg, fc_home.longitude_deg, fc_home.altitude_amsl_m) == \
            pytest.approx((HOME.lat_deg, HOME.lon_deg, HOME.alt_m), abs=1e-6)
        gp = g.recv("GLOBAL_POSITION_INT", timeout_s=5)
        assert abs(gp.lat / 1e7 - HOME.lat_deg) < 1e-5 and abs(gp.lon / 1e7 - HOME.lon_deg) < 1e-5
        assert abs(gp.alt / 1e3 - HOME.alt_m) < 0.5 and abs(gp.relative_alt / 1e3) < 0.5
        raw = g.recv("GPS_RAW_INT", lambda m: m.fix_type == M.GPS_FIX_TYPE_3D_FIX, timeout_s=5)   # the sim's GPS
        assert abs(raw.lat / 1e7 - HOME.lat_deg) < 1e-5 and abs(raw.lon / 1e7 - HOME.lon_deg) < 1e-5
        g.conn.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_HOME_POSITION,
                                     0, 0, 0, 0, 0, 0)
        hp = g.recv("HOME_POSITION", timeout_s=5)
        assert (hp.latitude, hp.longitude, hp.altitude) == \
            (round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7), round(HOME.alt_m * 1e3))
        assert abs(PARAM_HOME.lat_deg - HOME.lat_deg) > 1.0    # (the fallback is far away: a real check)
        g.recv("SYS_STATUS", lambda m: m.voltage_battery not in (0, 0xFFFF), timeout_s=5)

        # capabilities
        g.conn.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, 148, 0, 0, 0, 0, 0, 0)
        av = g.recv("AUTOPILOT_VERSION")
        assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        g.recv("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_REQUEST_MESSAGE and m.result == 0)

        # parameters: the list, one by name, a set that is accepted, a set that is rejected
        def param_list():
            g.conn.mav.param_request_list_send(1, 1)
            first = g.recv("PARAM_VALUE", timeout_s=5)
            got = {first.param_index: first}
            deadline = time.monotonic() + 5
            while len(got) < first.param_count and time.monotonic() < deadline:
                m = g.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)
                if m is not None:
                    got[m.param_index] = m
            assert len(got) == first.param_count
            return {m.param_id: m for m in got.values()}

        params = None
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:   # the table fills as the services answer
            params = param_list()
            if {"PLN_MAX_VELOCITY", "PLN_KP", "MIS_TAKEO_ALTITU"} <= set(params):
                break
            time.sleep(0.5)
        assert "PLN_MAX_VELOCITY" in params and params["PLN_MAX_VELOCITY"].param_value == pytest.approx(2.0)
        g.conn.mav.param_set_send(1, 1, b"PLN_MAX_VELOCITY", 3.5, M.MAV_PARAM_TYPE_REAL32)
        pv = g.recv("PARAM_VALUE", lambda m: m.param_id == "PLN_MAX_VELOCITY")
        assert pv.param_value == pytest.approx(3.5)
        g.conn.mav.param_set_send(1, 1, b"PLN_MAX_VELOCITY", 99.0, M.MAV_PARAM_TYPE_REAL32)   # above max
        pv = g.recv("PARAM_VALUE", lambda m: m.param_id == "PLN_MAX_VELOCITY")
        assert pv.param_value == pytest.approx(3.5)

        # DO_CHANGE_SPEED: the planner's live speed limit (ground speed 2.5; above max refused;
        # -2 = back to the planner's default)
        def change_speed(speed):
            g.conn.mav.command_long_send(1, 1, M.MAV_CMD_DO_CHANGE_SPEED, 0, 1, speed, -1, 0, 0, 0, 0)
            return g.recv("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_CHANGE_SPEED
                          and m.result != M.MAV_RESULT_IN_PROGRESS, timeout_s=8).result

        assert change_speed(2.5) == M.MAV_RESULT_ACCEPTED
        assert st.aero("param", "get", "planner", "max_velocity_mps").stdout.strip() == "2.5"
        assert change_speed(99.0) == M.MAV_RESULT_DENIED
        g.conn.mav.param_request_read_send(1, 1, b"PLN_MAX_VELOCITY", -1)
        assert g.recv("PARAM_VALUE", lambda m: m.param_id == "PLN_MAX_VELOCITY").param_value == pytest.approx(2.5)
        assert change_speed(-2.0) == M.MAV_RESULT_ACCEPTED
        assert st.aero("param", "get", "planner", "max_velocity_mps").stdout.strip() == "2.0"

        # mission upload (takeoff + 4 waypoints), then download
        pts = waypoints()
        items = [(M.MAV_CMD_NAV_TAKEOFF, HOME.lat_deg, HOME.lon_deg, 4.0)] + \
                [(M.MAV_CMD_NAV_WAYPOINT, *p) for p in pts]
        g.conn.mav.mission_count_send(1, 1, len(items), 0)
        for _ in items:
            req = g.recv("MISSION_REQUEST_INT")
            cmd, lat, lon, alt = items[req.seq]
            g.conn.mav.mission_item_int_send(1, 1, req.seq, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd, 0, 1,
                                             0, 0, 0, math.nan, int(lat * 1e7), int(lon * 1e7), alt, 0)
        ack = g.recv("MISSION_ACK")
        assert ack.type == M.MAV_MISSION_ACCEPTED
        ms = wait_for_message(st.session, "mission/status", MissionStatus,
                              lambda m: m.total_waypoints == 4, timeout_s=5)
        assert ms.mission_id.startswith("gcs")
        # the plan's id: in the ACK (opaque_id) and in MISSION_CURRENT (mission_id extension field)
        plan = extension_fields(ack)["opaque_id"]
        assert plan != 0
        mc = g.recv("MISSION_CURRENT", lambda m: m.total == len(items))
        assert extension_fields(mc)["mission_id"] == plan

        g.conn.mav.mission_request_list_send(1, 1, 0)
        cnt = g.recv("MISSION_COUNT")
        assert cnt.count == len(items)
        for i in range(cnt.count):
            g.conn.mav.mission_request_int_send(1, 1, i, 0)
            it = g.recv("MISSION_ITEM_INT", lambda m, i=i: m.seq == i)
            assert it.command == items[i][0] and it.x == int(items[i][1] * 1e7)
        g.conn.mav.mission_ack_send(1, 1, 0, 0)

        # a mission the stack refuses (an unsupported command) -> error ACK, previous one stays
        g.conn.mav.mission_count_send(1, 1, 1, 0)
        g.recv("MISSION_REQUEST_INT")
        g.conn.mav.mission_item_int_send(1, 1, 0, 3, M.MAV_CMD_NAV_LOITER_UNLIM, 0, 1, 0, 0, 0, 0,
                                         int(HOME.lat_deg * 1e7), int(HOME.lon_deg * 1e7), 5.0, 0)
        assert g.recv("MISSION_ACK").type == M.MAV_MISSION_UNSUPPORTED
        g.conn.mav.mission_request_list_send(1, 1, 0)
        assert g.recv("MISSION_COUNT").count == len(items)

        # a waypoint at home altitude (relative frame): refused, the STATUSTEXT names the item
        g.conn.mav.mission_count_send(1, 1, 2, 0)
        for _ in range(2):
            req = g.recv("MISSION_REQUEST_INT")
            lat, lon, _ = pts[req.seq]
            g.conn.mav.mission_item_int_send(1, 1, req.seq, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT,
                                             0, 1, 0, 0, 0, math.nan, int(lat * 1e7), int(lon * 1e7),
                                             5.0 if req.seq == 0 else 0.0, 0)
        text = g.recv("STATUSTEXT", lambda m: m.chunk_seq == 0)
        text2 = g.recv("STATUSTEXT", lambda m: m.id == text.id and m.chunk_seq == 1)
        assert text.severity == M.MAV_SEVERITY_CRITICAL
        assert (text.text + text2.text).startswith("Mission rejected: item 1: waypoint altitude 0.0 m")
        assert g.recv("MISSION_ACK").type == M.MAV_MISSION_INVALID_PARAM7
        g.conn.mav.mission_request_list_send(1, 1, 0)
        assert extension_fields(g.recv("MISSION_COUNT", lambda m: m.count == len(items)))["opaque_id"] == plan

        # a mission loaded without the ground station (aero mission load) is what a download shows
        square = Path(__file__).resolve().parents[2] / "examples" / "missions" / "square_20m.json"
        r = st.aero("mission", "load", str(square))
        assert r.returncode == 0, r.stderr

        def download():
            g.conn.mav.mission_request_list_send(1, 1, 0)
            n = g.recv("MISSION_COUNT").count
            got = []
            for i in range(n):
                g.conn.mav.mission_request_int_send(1, 1, i, 0)
                got.append(g.recv("MISSION_ITEM_INT", lambda m, i=i: m.seq == i))
            g.conn.mav.mission_ack_send(1, 1, 0, 0)
            return got

        deadline = time.monotonic() + 10
        while len(down := download()) != 6 and time.monotonic() < deadline:   # takeoff + 5 waypoints
            time.sleep(0.5)
        assert [d.command for d in down] == [M.MAV_CMD_NAV_TAKEOFF] + [M.MAV_CMD_NAV_WAYPOINT] * 5
        assert down[0].z == pytest.approx(4.0)
        mc = g.recv("MISSION_CURRENT", lambda m: m.total == 6)
        assert extension_fields(mc)["mission_id"] not in (0, plan)     # a changed mission, noticed
        lat, lon, alt = HOME.to_geodetic(10.0, -10.0, 4.0)                     # waypoint 0, ENU
        assert (down[1].x / 1e7, down[1].y / 1e7, down[1].z) == pytest.approx((lat, lon, alt), abs=1e-6)

        # garbage on the link is counted, never fatal
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for junk in (b"\xfd\x09garbage", bytes(range(256)), b"\xfe" * 40):
            raw.sendto(junk, ("127.0.0.1", port))
        raw.close()

        # arm: the real outcome from fmu/srv/arm, within bounded time
        g.conn.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = g.recv("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_COMPONENT_ARM_DISARM
                     and m.result != M.MAV_RESULT_IN_PROGRESS, timeout_s=8)
        assert ack.result == M.MAV_RESULT_ACCEPTED
        g.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1 and m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout_s=5)
        g.conn.mav.command_long_send(1, 1, 31999, 0, 0, 0, 0, 0, 0, 0, 0)
        assert g.recv("COMMAND_ACK", lambda m: m.command == 31999).result == M.MAV_RESULT_UNSUPPORTED
        g.conn.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0)
        ack = g.recv("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_COMPONENT_ARM_DISARM
                     and m.result != M.MAV_RESULT_IN_PROGRESS, timeout_s=8)
        assert ack.result == M.MAV_RESULT_ACCEPTED
        assert st.alive("gcs")
    finally:
        g.close()


def test_signing_refuses_unsigned_ground_stations(stack, tmp_path):
    """gcs with --signing-key-file: a pymavlink ground station signing with the same key works
    (signed telemetry, parameters, gcs/link up); one that does not sign is ignored (no answer, not
    a link) and counted in diagnostics/gcs; the key appears in no log."""
    key = os.urandom(32)
    key_file = tmp_path / "gcs.key"
    key_file.write_text(key.hex() + "\n")
    key_file.chmod(0o600)
    port = free_udp_port()
    st = stack(["gcs"], extra_args=[
        "--arg", f"gcs:--local-port={port}", "--arg", f"gcs:--remote-port={free_udp_port()}",
        "--arg", "gcs:--bind-ip=127.0.0.1", "--arg", f"gcs:--signing-key-file={key_file}",
        "--arg", "gcs:--signing-link-id=5"], timeout_s=30)
    signed, plain = Gcs(port), Gcs(port, system_id=254)
    signed.conn.setup_signing(key, sign_outgoing=True, link_id=1)   # refuses anything unsigned itself
    try:
        # the unsigned one: heartbeats and a parameter request, never answered
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            plain.heartbeat()
            plain.conn.mav.param_request_read_send(1, 1, b"GCS_SYSTEM_ID", -1)
            assert plain.conn.recv_match(blocking=True, timeout=0.3) is None
        hb = signed.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout_s=5)
        assert hb._signed and hb._link_id == 5
        signed.conn.mav.param_request_read_send(1, 1, b"GCS_SYSTEM_ID", -1)
        pv = signed.recv("PARAM_VALUE", lambda m: m.param_id == "GCS_SYSTEM_ID")
        assert pv._signed
        link = wait_for_message(st.session, "gcs/link", GcsLink, lambda m: m.connected, timeout_s=5)
        assert link.system_id == 255
        diag = wait_for_message(st.session, "diagnostics/gcs", DiagnosticStatus,
                                lambda d: int(d.values.get("mavlink_invalid[unsigned]", 0)) >= 6, timeout_s=5)
        assert diag.values["signing"] == "True" and int(diag.values["signing_rejected"]) >= 6
        assert diag.values["ground_stations"] == "1" and diag.level == DiagnosticStatus.WARN
        assert diag.values["home_source"] == "param"     # no flight controller: the parameters' home
        assert signed.conn.mav.signing.badsig_count == 0
        assert st.alive("gcs")
    finally:
        signed.close()
        plain.close()
    log = st.service_log("gcs")
    started = [json.loads(line) for line in log.splitlines() if '"gcs_link"' in line]
    assert started and started[0]["signing"] is True and started[0]["signing_key"] == f"file {key_file}"
    assert key.hex() not in log and key.hex().upper() not in log


def test_mavsdk_ground_station(stack):
    """MAVSDK-Python 4.x (in-process): connect, all params, set a float, mission_raw up/down, arm."""
    pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.mission_raw.mission_raw import MissionRawAsync
    from mavsdk.asyncio.plugins.param.param import ParamAsync
    from mavsdk.plugins.mission_raw import MissionItem

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)   # gcs sends to MAVSDK's udpin port before it talks
    pts = waypoints()

    async def session():
        async with mavsdk_autopilot(sdk_port) as system:
            param = ParamAsync(system)
            names: set[str] = set()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:   # until the table has every service's parameters
                allp = await asyncio.wait_for(param.get_all_params(), 20)
                names = {p.name for p in allp.float_params} | {p.name for p in allp.int_params}
                if {"PLN_MAX_VELOCITY", "MIS_TAKEO_ALTITU"} <= names:
                    break
                await asyncio.sleep(1.0)
            assert {"PLN_MAX_VELOCITY", "PLN_KP", "MIS_TAKEO_ALTITU", "GCS_SYSTEM_ID"} <= names
            await asyncio.wait_for(param.set_param_float("PLN_KP", 1.25), 10)
            assert await asyncio.wait_for(param.get_param_float("PLN_KP"), 10) == pytest.approx(1.25)

            raw = MissionRawAsync(system)
            items = []
            for i, (lat, lon, alt) in enumerate(pts):
                items.append(MissionItem(seq=i, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                         command=M.MAV_CMD_NAV_WAYPOINT, current=1 if i == 0 else 0,
                                         autocontinue=1, param1=0.0, param2=0.5, param3=0.0,
                                         param4=float("nan"), x=int(round(lat * 1e7)), y=int(round(lon * 1e7)),
                                         z=alt, mission_type=0))
            await asyncio.wait_for(raw.upload_mission(items), 20)
            down = await asyncio.wait_for(raw.download_mission(), 20)
            assert [(d.seq, d.command, d.x, d.y) for d in down] == [(i.seq, i.command, i.x, i.y) for i in items]
            assert all(d.z == pytest.approx(i.z) for d, i in zip(down, items))

            action = ActionAsync(system)
            await asyncio.wait_for(action.arm(), 15)
            await asyncio.wait_for(action.disarm(), 15)

    asyncio.run(asyncio.wait_for(session(), 120))
    ms = wait_for_message(st.session, "mission/status", MissionStatus, lambda m: m.total_waypoints == 4, timeout_s=5)
    assert ms.mission_id.startswith("gcs")


# ---------------------------------------------------------------- MAVProxy


def mavproxy_installed() -> bool:
    """MAVProxy runs as `python -m MAVProxy.mavproxy` with this interpreter (not a `mavproxy.py`
    found on PATH, which may be a pyenv shim or another Python's script)."""
    return importlib.util.find_spec("MAVProxy") is not None


class MavProxy:
    """MAVProxy driven through its stdin (a pipe), stdout read line by line in a thread.

    Interactive mode on purpose: --non-interactive / --daemon do not read stdin at all. No GUI
    modules (no --console/--map), --no-state (no logs, no aircraft dir), HOME and cwd in a
    temporary directory (no ~/.mavproxy, no ~/.mavinit.scr), DISPLAY unset."""

    def __init__(self, master: str, workdir: Path):
        if not mavproxy_installed():
            pytest.fail("MAVProxy is not installed (pip install -e '.[test]')")
        workdir.mkdir(parents=True, exist_ok=True)
        env = {k: v for k, v in os.environ.items() if k != "DISPLAY" and not k.startswith("AERO_")}
        env.update(HOME=str(workdir), PYTHONUNBUFFERED="1", MAVLINK20="1")
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "MAVProxy.mavproxy", f"--master={master}", "--no-state", "--source-system=255",
             "--source-component=190"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            bufsize=1, cwd=workdir, env=env)
        self._reader = threading.Thread(target=self._read, name="mavproxy-stdout", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.lines)

    def send(self, command: str) -> int:
        """Type one command; returns the output position before it (for expect(after=...))."""
        mark = self.mark()
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return mark

    def expect(self, pattern: str, timeout_s: float = 5.0, after: int = 0) -> re.Match:
        """The first output line at or after `after` matching `pattern` (bounded wait)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        i = after
        with self._cond:
            while True:
                while i < len(self.lines):
                    m = rx.search(self.lines[i])
                    i += 1
                    if m:
                        return m
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None and i >= len(self.lines):
                    raise AssertionError(f"MAVProxy printed nothing matching {pattern!r} within {timeout_s} s; "
                                         f"output:\n" + "\n".join(self.lines[-60:]))
                self._cond.wait(min(left, 0.2))

    def all_after(self, pattern: str, after: int) -> list[re.Match]:
        rx = re.compile(pattern)
        with self._cond:
            return [m for m in (rx.search(ln) for ln in self.lines[after:]) if m]

    def stop(self) -> None:
        """EOF on stdin is MAVProxy's clean exit; then SIGTERM, then kill (by handle)."""
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        for sig in (None, "terminate", "kill"):
            if sig is not None and self.proc.poll() is None:
                getattr(self.proc, sig)()
            try:
                self.proc.wait(8.0 if sig is None else 5.0)
                break
            except subprocess.TimeoutExpired:
                continue
        self._reader.join(2.0)


def write_qgc_wpl(path: Path, takeoff_alt: float, pts) -> list[tuple[int, float, float, float]]:
    """A QGC WPL 110 file as a PX4 ground station writes it (no home line: PX4 missions start at
    seq 0): NAV_TAKEOFF above home, then NAV_WAYPOINTs, global-relative frame."""
    rows = [(M.MAV_CMD_NAV_TAKEOFF, HOME.lat_deg, HOME.lon_deg, takeoff_alt)] + \
           [(M.MAV_CMD_NAV_WAYPOINT, *p) for p in pts]
    lines = ["QGC WPL 110"]
    for seq, (cmd, lat, lon, alt) in enumerate(rows):
        p2 = 0.5 if cmd == M.MAV_CMD_NAV_WAYPOINT else 0.0
        lines.append(f"{seq}\t{1 if seq == 0 else 0}\t{M.MAV_FRAME_GLOBAL_RELATIVE_ALT}\t{cmd}\t0\t{p2}\t0\t0\t"
                     f"{lat:.8f}\t{lon:.8f}\t{alt:.3f}\t1")
    path.write_text("\n".join(lines) + "\n")
    return rows


def test_mavproxy_ground_station(stack, tmp_path):
    """MAVProxy (scripted through stdin): parameters (MAVFTP NAKed -> plain protocol at once),
    get/set/refused set, mission load + list, mode, arm, disarm."""
    port, mp_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, mp_port)   # gcs sends to MAVProxy's udpin port until it talks
    mp = MavProxy(f"udpin:127.0.0.1:{mp_port}", tmp_path / "mavproxy")
    try:
        mp.expect(r"Detected vehicle 1:1", timeout_s=30)
        t0 = time.monotonic()
        mp.expect(r"Received \d+ parameters", timeout_s=10)   # MAVFTP would cost ~11 s before the fallback
        assert time.monotonic() - t0 < 10

        # planner kp: fetched by name (the table fills as the services answer), shown, set
        value = None
        deadline = time.monotonic() + 15
        while value is None and time.monotonic() < deadline:
            mark = mp.send("param fetch PLN_KP")
            try:
                value = float(mp.expect(r"PLN_KP = (-?[\d.]+)", timeout_s=2, after=mark).group(1))
            except AssertionError:
                time.sleep(0.5)
        assert value == pytest.approx(0.8)
        mark = mp.send("param show PLN_KP")
        assert float(mp.expect(r"PLN_KP\s+(-?[\d.]+)\s*$", after=mark).group(1)) == pytest.approx(0.8)

        mp.send("param set PLN_KP 1.1")
        got = wait_until_value(lambda: st.aero("param", "get", "planner", "kp", timeout_s=10).stdout.strip(),
                               "1.1", timeout_s=10)
        assert got == "1.1"   # the planner holds 1.1, not the float32 1.100000023841858
        mark = mp.send("param fetch PLN_KP")
        assert float(mp.expect(r"PLN_KP = (-?[\d.]+)", after=mark).group(1)) == pytest.approx(1.1)

        # above the declared max (5.0): the planner refuses, gcs echoes the value in force,
        # MAVProxy retries and gives up
        mark = mp.send("param set PLN_KP 9")
        mp.expect(r"Failed to set PLN_KP to 9", timeout_s=10, after=mark)
        assert st.aero("param", "get", "planner", "kp").stdout.strip() == "1.1"

        # mission: load a QGC WPL file (takeoff + 4 waypoints), then list it back
        wpl = tmp_path / "square.txt"
        rows = write_qgc_wpl(wpl, 4.0, waypoints())
        mark = mp.send(f"wp load {wpl}")
        mp.expect(rf"Sent all {len(rows)} waypoints", timeout_s=10, after=mark)
        mp.expect(r"Got MISSION_ACK: TYPE_MISSION: ACCEPTED", timeout_s=10, after=mark)
        ms = wait_for_message(st.session, "mission/status", MissionStatus, lambda m: m.total_waypoints == 4,
                              timeout_s=5)
        assert ms.mission_id.startswith("gcs")

        mark = mp.send("wp list")
        mp.expect(rf"Requesting {len(rows)} waypoints", timeout_s=5, after=mark)
        item_rx = r"(\d+) (\d+) (-?\d+\.\d+) (-?\d+\.\d+) (-?\d+\.\d+) p1="
        mp.expect(item_rx, after=mark)
        wait_until(lambda: len(mp.all_after(item_rx, mark)) >= len(rows), 5, "wp list output")
        listed = mp.all_after(item_rx, mark)[:len(rows)]
        for m, (cmd, lat, lon, alt) in zip(listed, rows):
            assert int(m.group(1)) == cmd and int(m.group(2)) == M.MAV_FRAME_GLOBAL_RELATIVE_ALT
            assert float(m.group(3)) == pytest.approx(lat, abs=2e-7) and float(m.group(4)) == pytest.approx(lon, abs=2e-7)
            assert float(m.group(5)) == pytest.approx(alt)

        # mode: MAVProxy 1.8's `mode LOITER` is broken against PX4 (it passes pymavlink's
        # (base, main, sub) tuple as one float), so send DO_SET_MODE itself: PX4 AUTO.LOITER = HOLD
        mark = mp.send(f"long DO_SET_MODE {M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED} 4 3")
        mp.expect(r"Got COMMAND_ACK: DO_SET_MODE: ACCEPTED", timeout_s=8, after=mark)

        mark = mp.send("arm throttle")
        mp.expect(r"Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED", timeout_s=8, after=mark)
        mp.expect(r"^(?:\S+> )*ARMED", timeout_s=5, after=mark)
        mark = mp.send("disarm")
        mp.expect(r"Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED", timeout_s=8, after=mark)
        mp.expect(r"DISARMED", timeout_s=5, after=mark)
        assert st.alive("gcs")
    finally:
        mp.stop()
    assert mp.proc.returncode is not None


def wait_until_value(get, want, timeout_s=10.0, interval_s=0.3):
    """Poll get() until it returns `want`; the last value either way."""
    deadline = time.monotonic() + timeout_s
    value = get()
    while value != want and time.monotonic() < deadline:
        time.sleep(interval_s)
        value = get()
    return value


# ---------------------------------------------------------------- a mission flown end to end


@pytest.mark.slow
@pytest.mark.extended   # 26 s; test_gcs_px4_compat flies a MAVSDK mission to is_mission_finished by default
def test_mavsdk_mission_flies_in_sim(stack):
    """MAVSDK uploads takeoff + DO_CHANGE_SPEED + 4 waypoints (a 4 m square at 3 m), arms and
    starts the mission; the speed item sets the planner's speed when the mission starts (not at
    upload) and only for the mission (back to 2.0 once it is over); every waypoint's MISSION_ITEM_REACHED arrives at the ground station in order, the
    vehicle lands and disarms (simulator ground truth, fmu's vehicle status), all within 90 s.
    The takeoff item's MISSION_ITEM_REACHED comes first, as PX4 sends it when the takeoff is done."""
    pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.mavlink_direct.mavlink_direct import MavlinkDirectAsync
    from mavsdk.asyncio.plugins.mission_raw.mission_raw import MissionRawAsync
    from mavsdk.asyncio.plugins.telemetry.telemetry import TelemetryAsync
    from mavsdk.plugins.mission_raw import MissionItem

    from aeroperception.schemas import VehicleState, VehicleStatus, WaypointReached

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)
    wait_until(lambda: (m := st.latest("state/vehicle", VehicleState, 1.0)) is not None and m.connected, 15,
               "state/vehicle connected (fmu <-> sim)")
    alt = 3.0
    pts = waypoints(alt=alt)
    speed = 2.5
    rows = [(M.MAV_CMD_NAV_TAKEOFF, HOME.lat_deg, HOME.lon_deg, alt), (M.MAV_CMD_DO_CHANGE_SPEED, 0.0, 0.0, 0.0)] \
        + [(M.MAV_CMD_NAV_WAYPOINT, *p) for p in pts]

    def item(i, cmd, lat, lon, z):
        if cmd == M.MAV_CMD_DO_CHANGE_SPEED:
            return MissionItem(seq=i, frame=M.MAV_FRAME_MISSION, command=cmd, current=0, autocontinue=1,
                               param1=1.0, param2=speed, param3=-1.0, param4=0.0, x=0, y=0, z=0.0, mission_type=0)
        return MissionItem(seq=i, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=cmd, current=1 if i == 0 else 0,
                           autocontinue=1, param1=0.0, param2=0.5 if cmd == M.MAV_CMD_NAV_WAYPOINT else 0.0,
                           param3=0.0, param4=float("nan"), x=int(round(lat * 1e7)), y=int(round(lon * 1e7)),
                           z=z, mission_type=0)

    items = [item(i, *r) for i, r in enumerate(rows)]
    planner_speed = lambda: st.aero("param", "get", "planner", "max_velocity_mps").stdout.strip()  # noqa: E731
    wp_seqs = [i for i, r in enumerate(rows) if r[0] == M.MAV_CMD_NAV_WAYPOINT]
    reached: list[int] = []
    progress: list[tuple[int, int]] = []
    timing: dict[str, float] = {}
    planner_speed_seen: list[float] = []

    async def collect_reached(direct):
        async for msg in direct.subscribe_message("MISSION_ITEM_REACHED"):
            reached.append(int(json.loads(msg.fields_json)["seq"]))

    async def collect_progress(raw):
        async for p in raw.subscribe_mission_progress():
            progress.append((p.current, p.total))

    async def until(pred, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; reached {reached}, "
                                     f"progress {progress[-3:]}")
            await asyncio.sleep(0.1)

    async def session():
        async with mavsdk_autopilot(sdk_port) as system:
            raw, action, tel = MissionRawAsync(system), ActionAsync(system), TelemetryAsync(system)
            tasks = [asyncio.create_task(collect_reached(MavlinkDirectAsync(system))),
                     asyncio.create_task(collect_progress(raw))]
            armed: list[bool] = []

            async def collect_armed():
                async for a in tel.subscribe_armed():
                    armed.append(a)
            tasks.append(asyncio.create_task(collect_armed()))
            try:
                await asyncio.wait_for(raw.upload_mission(items), 20)
                timing["speed_after_upload"] = await asyncio.to_thread(planner_speed)

                async def collect_speed():
                    while True:
                        v = await asyncio.to_thread(planner_speed)
                        if v and v != "2.0" and float(v) not in planner_speed_seen:
                            planner_speed_seen.append(float(v))
                        await asyncio.sleep(0.3)
                tasks.append(asyncio.create_task(collect_speed()))
                t0 = time.monotonic()
                await asyncio.wait_for(action.arm(), 15)
                await asyncio.wait_for(raw.start_mission(), 15)
                await until(lambda: planner_speed_seen, 30, "the mission's speed in force")
                await until(lambda: len(reached) >= len(rows), 60,
                            "MISSION_ITEM_REACHED for the takeoff and every waypoint")
                timing["waypoints_s"] = time.monotonic() - t0
                await until(lambda: armed and not armed[-1], 30, "MAVSDK telemetry: disarmed")
                timing["flight_s"] = time.monotonic() - t0
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    rec = Capture(st.session, {"truth": ("sim/truth/state", VehicleState),
                                "vstatus": ("fmu/out/vehicle_status", VehicleStatus),
                                "status": ("mission/status", MissionStatus),
                                "reached": ("mission/waypoint_reached", WaypointReached)})
    try:
        asyncio.run(asyncio.wait_for(session(), 110))
        wait_until(lambda: rec.last("vstatus") is not None and not rec.last("vstatus").armed, 5,
                   "fmu/out/vehicle_status disarmed")
        wait_until(lambda: rec.last("status") is not None and rec.last("status").state == "IDLE", 5, "mission IDLE")
        truth = rec.get("truth")
        states = [m.state for m in rec.get("status")]
    finally:
        rec.close()
    print(f"gcs mission: waypoints after {timing['waypoints_s']:.1f} s, landed+disarmed after "
          f"{timing['flight_s']:.1f} s; reached {reached}; progress {sorted(set(progress))}")
    # every item, in order, once each: the takeoff, the DO_CHANGE_SPEED after it (it runs
    # once the takeoff is done), then every waypoint including the last
    assert reached == list(range(len(rows)))
    assert timing["speed_after_upload"] == "2.0" and planner_speed_seen == [speed]
    assert wait_until_value(planner_speed, "2.0", timeout_s=5) == "2.0"   # mission-scoped: restored
    assert timing["flight_s"] < 90
    assert truth and truth[-1].position_m.z < 0.2 and max(m.position_m.z for m in truth) > alt - 0.5
    track = np.array([m.position_m.to_array() for m in truth])
    for seq in wp_seqs:
        lat, lon, z = rows[seq][1:]
        target = np.array(HOME.to_enu(lat, lon, z))
        assert np.linalg.norm(track - target, axis=1).min() < 0.6, f"item {seq}: never within 0.6 m of {target}"
    order = [s for i, s in enumerate(states) if i == 0 or states[i - 1] != s]
    assert [s for s in order if s in ("TAKEOFF", "EXECUTING", "LAND")][:3] == ["TAKEOFF", "EXECUTING", "LAND"]
    assert order[-1] == "IDLE"
    assert progress and progress[-1] == (len(rows), len(rows))   # MAVSDK: mission finished
