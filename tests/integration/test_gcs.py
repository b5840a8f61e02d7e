"""gcs against a real stack (sim + fmu + planner + mission + gcs over Zenoh), driven by real
ground-station software: pymavlink first, then MAVSDK-Python. Loopback only, free ports."""
from __future__ import annotations

import asyncio
import math
import os
import socket
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aeroperception.schemas import GcsLink, MissionStatus, decode  # noqa: E402
from aeroperception.services.gcs.missions import Home  # noqa: E402
from aerotest import wait_for_message  # noqa: E402

HOME = Home(35.736805, 139.539676, 10.0)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_stack(stack, gcs_port: int, gcs_remote: int):
    p1, p2 = free_udp_port(), free_udp_port()
    return stack(["sim", "fmu", "planner", "mission", "gcs"], extra_args=[
        "--arg", f"fmu:--fcu-url=udpin:127.0.0.1:{p1}", "--arg", f"sim:--target=127.0.0.1:{p1}",
        "--arg", f"sim:--bind=127.0.0.1:{p2}", "--arg", "sim:--sensors=none",
        "--arg", f"gcs:--local-port={gcs_port}", "--arg", f"gcs:--remote-port={gcs_remote}",
        "--arg", "gcs:--bind-ip=127.0.0.1"], timeout_s=40)


class Gcs:
    """A pymavlink ground station that talks first (gcs learns our address)."""

    def __init__(self, gcs_port: int):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=255,
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

        # telemetry from the stack's state: home about the seed's default, local NED
        gp = g.recv("GLOBAL_POSITION_INT", timeout_s=5)
        assert abs(gp.lat / 1e7 - HOME.lat_deg) < 1e-4 and abs(gp.lon / 1e7 - HOME.lon_deg) < 1e-4
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


def test_mavsdk_ground_station(stack):
    """MAVSDK-Python 4.x (in-process): connect, all params, set a float, mission_raw up/down, arm."""
    mavsdk = pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.mission_raw.mission_raw import MissionRawAsync
    from mavsdk.asyncio.plugins.param.param import ParamAsync
    from mavsdk.plugins.mission_raw import MissionItem

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)   # gcs sends to MAVSDK's udpin port before it talks
    pts = waypoints()

    async def session():
        config = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
        async with mavsdk.Mavsdk(config) as sdk:
            await sdk.add_any_connection(f"udpin://127.0.0.1:{sdk_port}")
            system = await sdk.first_autopilot(timeout_s=15.0)
            assert system is not None, "MAVSDK saw no autopilot"
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
