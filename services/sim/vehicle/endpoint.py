"""MAVLink 2 over UDP, addressed like PX4 SITL's onboard link.

PX4 SITL binds a local port (14580) and sends to the companion's port (14540); the companion
(`udpin:127.0.0.1:14540`) replies to wherever the datagrams came from. A plain non-blocking UDP
socket does exactly that, with pymavlink's generated MAVLink class as encoder and parser
(pymavlink's own `udpout` cannot bind a chosen source port).

Each datagram is parsed on its own: a truncated or corrupt frame cannot swallow the start of
the next datagram. Anything that does not decode (bad magic, bad CRC, unknown message id,
truncation) is counted and dropped; nothing here raises on input.
"""
from __future__ import annotations

import errno
import select
import socket
from typing import Iterator

from pymavlink.dialects.v20 import common as mavlink

PX4_SITL_BIND = ("127.0.0.1", 14580)
PX4_SITL_TARGET = ("127.0.0.1", 14540)
_MAX_DATAGRAM = 65535


def parse_address(text: str) -> tuple[str, int]:
    """'host:port' -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


class _DatagramWriter:
    """File-like sink for pymavlink's encoder: one write() = one packed frame = one datagram."""

    def __init__(self, endpoint: "MavlinkEndpoint"):
        self._endpoint = endpoint

    def write(self, frame: bytes) -> None:
        self._endpoint._send_datagram(frame)


class MavlinkEndpoint:
    """A UDP MAVLink 2 link: `send(msg)` to the target, `receive()` whatever has arrived."""

    def __init__(self, target: tuple[str, int] = PX4_SITL_TARGET, bind: tuple[str, int] = PX4_SITL_BIND,
                 system_id: int = 1, component_id: int = mavlink.MAV_COMP_ID_AUTOPILOT1):
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)
        self.sock.setblocking(False)
        self._readable = select.poll()
        self._readable.register(self.sock, select.POLLIN)
        self.encoder = mavlink.MAVLink(_DatagramWriter(self), srcSystem=system_id, srcComponent=component_id)
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self.last_peer: tuple[str, int] | None = None
        self.counters = {"rx_datagrams": 0, "rx_msgs": 0, "rx_bad": 0, "tx_msgs": 0, "tx_errors": 0}

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send(self, msg: mavlink.MAVLink_message) -> None:
        self.encoder.send(msg)

    def _send_datagram(self, frame: bytes) -> None:
        try:
            self.sock.sendto(frame, self.target)
            self.counters["tx_msgs"] += 1
        except OSError:
            # Nobody listening (ICMP refused), buffer full: a lossy link, like UDP to PX4.
            self.counters["tx_errors"] += 1

    def receive(self, max_datagrams: int = 256) -> list[mavlink.MAVLink_message]:
        """Everything that arrived since the last call (non-blocking), decoded. Called every physics
        step, mostly with nothing there: a poll (0.3 us) says so cheaper than a recvfrom that raises
        BlockingIOError (1.6 us)."""
        out: list[mavlink.MAVLink_message] = []
        if not self._readable.poll(0):
            return out
        for _ in range(max_datagrams):
            try:
                data, peer = self.sock.recvfrom(_MAX_DATAGRAM)
            except BlockingIOError:
                break
            except OSError as e:
                if e.errno in (errno.ECONNREFUSED, errno.ECONNRESET):
                    continue  # ICMP error from an earlier send: not input
                break
            self.counters["rx_datagrams"] += 1
            self.last_peer = peer
            out.extend(self._decode(data))
        return out

    def _decode(self, data: bytes) -> Iterator[mavlink.MAVLink_message]:
        p = self._parser
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        try:
            msgs = p.parse_buffer(data) or []
        except Exception:  # robust_parsing should not raise; if pymavlink does, it is still bad input
            msgs = [None]
        leftover = p.buf_len() > 0
        for m in msgs:
            if m is None or m.get_type() == "BAD_DATA":
                self.counters["rx_bad"] += 1
            else:
                self.counters["rx_msgs"] += 1
                yield m
        if leftover:  # a frame cut short at the end of the datagram
            self.counters["rx_bad"] += 1

    def close(self) -> None:
        self.sock.close()
