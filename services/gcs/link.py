"""UDP MAVLink 2 link to the ground station (seed 001 §5.1), no Zenoh.

Binds `local_port`, sends to `gcs_ip:remote_port` until the first packet arrives, then to whoever
sent it (address learning: the ground station may start the conversation from anywhere).
Parsing is robust: garbage bytes, bad CRCs and unknown message ids are counted, never raised.
"""
from __future__ import annotations

import socket
import threading
from collections import Counter
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink

MAX_DATAGRAM = 65535


class _Writer:
    """pymavlink's MAVLink object writes encoded frames to `file.write`; we send them as datagrams."""

    def __init__(self, link: "UdpLink"):
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link.send_bytes(bytes(buf))


def make_mav(system_id: int = 1, component_id: int = 1, file=None) -> mavlink.MAVLink:
    """A MAVLink 2 encoder/decoder with our identity."""
    mav = mavlink.MAVLink(file, srcSystem=system_id, srcComponent=component_id, use_native=False)
    mav.robust_parsing = True
    return mav


class Parser:
    """Bytes -> MAVLink messages; invalid input is counted by reason, never raised."""

    def __init__(self, datagrams: bool = True):
        self.datagrams = datagrams  # each feed() is one UDP datagram
        self.mav = make_mav()
        self.invalid: Counter[str] = Counter()
        self.received = 0

    def feed(self, data: bytes) -> list[mavlink.MAVLink_message]:
        out = []
        try:
            msgs = self.mav.parse_buffer(data) or []
        except Exception as e:  # noqa: BLE001 - pymavlink raises on some malformed frames
            self.invalid[type(e).__name__] += 1
            self.mav.buf = bytearray()
            self.mav.buf_index = 0
            return out
        for m in msgs:
            if isinstance(m, mavlink.MAVLink_unknown) or m.get_type().startswith("UNKNOWN"):
                self.invalid["unknown_id"] += 1
                continue
            if m.get_type() == "BAD_DATA":
                reason = str(getattr(m, "reason", "bad data"))
                self.invalid["bad_crc" if "crc" in reason.lower() else "bad_data"] += 1
                continue
            self.received += 1
            out.append(m)
        if self.datagrams and len(self.mav.buf) - self.mav.buf_index > 0:
            # A frame never spans datagrams: whatever is left is a truncated frame. Drop it so
            # the next datagram starts in sync.
            self.invalid["truncated"] += 1
            self.mav.buf = bytearray()
            self.mav.buf_index = 0
        return out

    @property
    def invalid_total(self) -> int:
        return sum(self.invalid.values())


class UdpLink:
    """The socket, the learnt peer address and the MAVLink encoder (thread-safe send)."""

    def __init__(self, bind_ip: str, local_port: int, gcs_ip: str, remote_port: int,
                 system_id: int = 1, component_id: int = 1):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((bind_ip, local_port))
        self.sock.settimeout(0.2)
        self.local_address = self.sock.getsockname()
        self.remote: tuple[str, int] = (gcs_ip, remote_port)
        self.learnt = False
        self.mav = make_mav(system_id, component_id, _Writer(self))
        self.parser = Parser()
        self._send_lock = threading.Lock()
        self.sent = 0
        self.send_errors = 0
        self.datagrams = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------ send

    def send_bytes(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.remote)
            self.sent += 1
        except OSError:
            self.send_errors += 1

    def send(self, msg: mavlink.MAVLink_message) -> None:
        """Encode (our sysid/compid, next sequence number) and send one message."""
        with self._send_lock:
            self.mav.send(msg)

    # ------------------------------------------------------------ receive

    def handle_datagram(self, data: bytes, addr: tuple[str, int]) -> list[mavlink.MAVLink_message]:
        self.datagrams += 1
        msgs = self.parser.feed(data)
        if msgs and addr != self.remote:
            self.remote = addr  # seed 001 §5.1: the ground station's first packet sets the address
            self.learnt = True
        return msgs

    def start(self, on_message: Callable[[mavlink.MAVLink_message], None]) -> None:
        def loop() -> None:
            while not self._stop.is_set():
                try:
                    data, addr = self.sock.recvfrom(MAX_DATAGRAM)
                except socket.timeout:
                    continue
                except OSError:
                    if self._stop.is_set():
                        return
                    continue
                for m in self.handle_datagram(data, addr):
                    on_message(m)

        self._thread = threading.Thread(target=loop, name="gcs-udp-rx", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        try:
            self.sock.close()
        except OSError:
            pass
