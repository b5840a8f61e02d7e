"""fmu's MAVLink link to the flight controller: who may talk to fmu, and noticing an FC reboot.

pymavlink's `udpin` binds with SO_REUSEADDR and answers every address that ever sent it a
datagram: 5 junk bytes got fmu's whole telemetry stream back, and a second socket bound to the
same port with address reuse silently took the autopilot link over. `LockedUdpIn` instead
- binds exclusively (no SO_REUSEADDR / SO_REUSEPORT): if anything already holds the port, or
  could share it, start-up fails with one line naming the port;
- locks onto the first sender of an autopilot HEARTBEAT (not a GCS or companion), or onto a
  pinned `fcu_peer`; datagrams from any other address are counted and dropped, and nothing is
  ever sent to them;
- re-locks only after the locked peer has been silent for `relock_after_s` (0: never), so a
  PX4 SITL restarted on another port is found again while a live link cannot be stolen.
"""
from __future__ import annotations

import errno
import socket
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

_NOT_AN_FC = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL,
              mavlink.MAV_TYPE_CAMERA, mavlink.MAV_TYPE_ADSB, mavlink.MAV_TYPE_ODID}


class LinkError(RuntimeError):
    """The link cannot be opened as asked (port taken, bad address)."""


def parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise LinkError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def is_autopilot_heartbeat(m) -> bool:
    return (m.get_type() == "HEARTBEAT" and m.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            and m.type not in _NOT_AN_FC)


class LockedUdpIn(mavutil.mavudp):
    """`udpin:HOST:PORT` bound exclusively, talking only to the flight controller's address."""

    def __init__(self, address: str, source_system: int, source_component: int,
                 pinned_peer: tuple[str, int] | None = None, relock_after_s: float = 3.0):
        host, port = parse_host_port(address)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))  # no address reuse: fails if any socket has or may share it
        except OSError as e:
            sock.close()
            why = "already in use (another fmu, MAVProxy or ground station?)" if e.errno == errno.EADDRINUSE \
                else e.strerror
            raise LinkError(f"cannot bind UDP {host}:{port} for the flight-controller link: {why}") from None
        sock.setblocking(False)
        mavutil.set_close_on_exec(sock.fileno())
        self.port = sock
        self.udp_server = True
        self.broadcast = False
        self.last_address = None
        self.timeout = 0
        self.clients, self.clients_last_alive = set(), {}
        self.resolved_destination_addr = None
        self.pinned = pinned_peer
        self.peer: tuple[str, int] | None = pinned_peer
        self.peer_rx_s = time.monotonic()
        self.relock_after_s = relock_after_s
        self.counters = {"rejected_datagrams": 0, "link_locks": 0}
        self.rejected_sources: set[tuple[str, int]] = set()
        self.events: list[tuple[str, dict]] = []  # (event, fields) for the shell to log
        self._probe = mavlink.MAVLink(None)
        self._probe.robust_parsing = True
        mavutil.mavfile.__init__(self, sock.fileno(), address, source_system=source_system,
                                 source_component=source_component, input=True)

    def _has_autopilot_heartbeat(self, data: bytes) -> bool:
        p = self._probe
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        try:
            msgs = p.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - junk is junk
            return False
        return any(m is not None and is_autopilot_heartbeat(m) for m in msgs)

    def accept(self, data: bytes, addr: tuple[str, int], now_s: float) -> bool:
        """Whether a datagram from `addr` goes to the parser (and may lock the link)."""
        if self.peer is not None and self.pinned is None and self.relock_after_s > 0 \
                and now_s - self.peer_rx_s > self.relock_after_s and addr != self.peer:
            self.events.append(("fcu_link_unlocked", dict(peer="%s:%d" % self.peer,
                                                          silent_s=round(now_s - self.peer_rx_s, 1))))
            self.peer = None
        if self.peer is None and self._has_autopilot_heartbeat(data):
            self.peer = addr
            self.counters["link_locks"] += 1
            self.events.append(("fcu_link_locked", dict(peer="%s:%d" % addr)))
        if addr == self.peer:
            self.peer_rx_s = now_s
            return True
        self.counters["rejected_datagrams"] += 1
        if addr not in self.rejected_sources and len(self.rejected_sources) < 64:
            self.rejected_sources.add(addr)
            self.events.append(("datagram_from_other_source_dropped", dict(source="%s:%d" % addr)))
        return False

    def recv(self, n=None):
        while True:
            try:
                data, addr = self.port.recvfrom(mavutil.UDP_MAX_PACKET_LEN)
            except OSError as e:
                if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return ""
                raise
            if self.accept(data, addr, time.monotonic()):
                return data

    def write(self, buf):
        if self.peer is None:
            return  # nobody to talk to yet: never answer an unknown sender
        try:
            self.port.sendto(buf, self.peer)
        except OSError:
            pass


def open_fcu_link(url: str, source_system: int, source_component: int, pinned_peer: str = "",
                  relock_after_s: float = 3.0):
    """`udpin:` -> LockedUdpIn; anything else (serial, tcp, udpout) -> pymavlink as before."""
    if url.startswith("udpin:"):
        pin = parse_host_port(pinned_peer) if pinned_peer else None
        return LockedUdpIn(url[len("udpin:"):], source_system, source_component, pin, relock_after_s)
    return mavutil.mavlink_connection(url, source_system=source_system, source_component=source_component,
                                      autoreconnect=True)


class RebootWatch:
    """Notices that the flight controller restarted: its time_boot_ms went backwards, or its
    heartbeat was missing for `gap_s`. Either way the link set-up (stream rates, home) is redone."""

    def __init__(self, gap_s: float = 2.0, backwards_tolerance_ms: int = 500):
        self.gap_s = gap_s
        self.tolerance_ms = backwards_tolerance_ms
        self.last_boot_ms: int | None = None
        self.last_heartbeat_s: float | None = None

    def on_heartbeat(self, now_s: float) -> str:
        """'' or why the FC may have rebooted."""
        last, self.last_heartbeat_s = self.last_heartbeat_s, now_s
        if last is not None and now_s - last >= self.gap_s:
            return f"no heartbeat for {now_s - last:.1f} s"
        return ""

    def on_boot_time(self, time_boot_ms: int) -> str:
        last, self.last_boot_ms = self.last_boot_ms, time_boot_ms
        if last is not None and time_boot_ms + self.tolerance_ms < last and last < 0xFFFFFFFF - 60_000:
            return f"time_boot_ms went back from {last} to {time_boot_ms}"
        return ""
