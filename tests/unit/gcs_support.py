"""What the gcs unit tests share: a ground station's messages as parsed off the wire, a home,
mission items, a mission protocol with a fake loader, and a fake of the stack's operations."""
from __future__ import annotations

import math
import socket
import time

from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.home import Home
from aeroperception.services.gcs.link import Parser, make_mav
from aeroperception.services.gcs.mission_items import Item, convert_items
from aeroperception.services.gcs.mission_protocol import MissionProtocol


HOME = Home(35.736805, 139.539676, 10.0)
GCS = make_mav(255, 190)


def from_gcs(msg):
    """A message as the ground station would send it (packed and parsed, so src ids are set)."""
    data = msg.pack(GCS)
    out = Parser().feed(data)
    assert len(out) == 1
    return out[0]


def from_mav(mav, msg):
    (m,) = Parser().feed(msg.pack(mav))
    return m


def item_int(seq, lat, lon, alt, cmd=M.MAV_CMD_NAV_WAYPOINT, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, **kw):
    return from_gcs(M.MAVLink_mission_item_int_message(
        1, 1, seq, frame, cmd, 0, 1, kw.get("p1", 0.0), kw.get("p2", 0.0), 0.0, kw.get("p4", math.nan),
        int(round(lat * 1e7)), int(round(lon * 1e7)), alt, 0))


class Loader:
    def __init__(self, accept=True, sync=True):
        self.accept, self.sync, self.calls, self.pending = accept, sync, [], None

    def __call__(self, items, done):
        self.calls.append(items)
        if self.sync:
            mission, _ = convert_items(items, HOME) if self.accept else (None, None)
            done(self.accept, "ok" if self.accept else "rejected", M.MAV_MISSION_DENIED)
        else:
            self.pending = done


def proto(loader=None, **kw):
    sent = []
    p = MissionProtocol(sent.append, loader or Loader(), **kw)
    return p, sent


def square(n=4, alt=5.0):
    out = []
    for i in range(n):
        north, east = (0, 10, 10, 0)[i % 4], (0, 0, 10, 10)[i % 4]
        lat, lon = HOME.projection.reproject(north, east)
        out.append((lat, lon, alt))
    return out


def upload(p, sent, points, now=0.0):
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, len(points), 0)), now)
    for i, (lat, lon, alt) in enumerate(points):
        req = sent[-1]
        assert req.get_type() == "MISSION_REQUEST_INT" and req.seq == i
        p.handle(item_int(i, lat, lon, alt), now)
    return sent[-1]


def speed_item(seq, speed, kind=1.0):
    return Item(seq=seq, frame=M.MAV_FRAME_MISSION, command=M.MAV_CMD_DO_CHANGE_SPEED, param1=kind, param2=speed,
                param3=-1.0)


def wp_item(seq, north, east, alt=5.0):
    lat, lon = HOME.projection.reproject(north, east)
    return Item(seq=seq, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_WAYPOINT,
                x=lat, y=lon, z=alt, param4=math.nan)


def takeoff_item(seq, alt=4.0):
    return Item(seq=seq, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=M.MAV_CMD_NAV_TAKEOFF,
                x=HOME.lat_deg, y=HOME.lon_deg, z=alt, param4=math.nan)


class FakeOps:
    def __init__(self):
        self.calls, self.dones = [], []

    def _rec(self, *a):
        self.calls.append(a[:-1])
        self.dones.append(a[-1])

    def arm(self, arm, force, done): self._rec("arm", arm, force, done)
    def set_mode(self, mode, done): self._rec("set_mode", mode, done)
    def mission_command(self, c, done): self._rec("mission", c, done)
    def mission_start(self, done): self._rec("start", done)
    def takeoff(self, alt, done): self._rec("takeoff", alt, done)
    def goto(self, enu, yaw, done): self._rec("goto", enu, yaw, done)
    def change_speed(self, speed, done): self._rec("speed", speed, done)


def cmd_long(cmd, *p):
    p = list(p) + [0.0] * (7 - len(p))
    return from_gcs(M.MAVLink_command_long_message(1, 1, cmd, 0, *p))


def udp_peer() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.02)
    return s


def drain(sock: socket.socket, wait_s: float = 0.3, until: int = 0) -> list:
    """The MAVLink messages arriving on `sock` within wait_s (sooner once `until` have arrived)."""
    out, parser = [], Parser()
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and not (until and len(out) >= until):
        try:
            data, _ = sock.recvfrom(65535)
        except socket.timeout:
            continue
        out += parser.feed(data)
    return out


def types(msgs) -> list[str]:
    return [m.get_type() for m in msgs]


def poll(pred, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


class FakeStack:
    """node.call_async: records each call (key, request) and keeps its reply callback, for the
    test to answer in order."""

    def __init__(self):
        self.calls, self.replies = [], []

    def __call__(self, key, request, reply_type, on_reply, timeout_s):
        self.calls.append((key, request))
        self.replies.append(on_reply)

    def answer(self, reply) -> None:
        self.replies.pop(0)(reply)

    def asked(self) -> list[tuple[str, object]]:
        """(key, the request's command, mode or parameter name) of every call."""
        return [(k, getattr(r, "command", None) or getattr(r, "mode", None) or getattr(r, "name", None))
                for k, r in self.calls]


class Log:
    """The service log: every event name, in order."""

    def __init__(self):
        self.events = []

    def info(self, event, **kw):
        self.events.append(event)

    warn = info
