"""UDP MAVLink 2 link to the ground stations, no Zenoh.

Binds `local_port`. Several ground stations may be connected at once; each is known by the UDP
address it sends from (address learning: a ground station may start the conversation from
anywhere). Where a message goes:

- telemetry and anything else sent without a recipient: to the initial `gcs_ip:remote_port`
  always (a listen-only ground station there, e.g. a second QGC or MAVSDK on 14550, must be able
  to connect while another station talks to us), plus every peer that has sent a HEARTBEAT within
  `timeout_s`; while none has, plus the last one heard (so one that restarted on the same address
  hears us again);
- a reply sent while a received message is being handled (same thread, synchronously: e.g.
  PARAM_VALUE for PARAM_REQUEST_LIST/READ, MISSION_REQUEST_INT, MISSION_COUNT, TIMESYNC,
  AUTOPILOT_VERSION for REQUEST_MESSAGE): to the address that message came from, only;
- a message sent later with a target (COMMAND_ACK, MISSION_ACK, ... after a call into the
  stack): to the address that target system/component last spoke from (all of that system's
  addresses when target_component is 0), else to everyone;
- `send(msg, peer=(sys, comp))` (STATUSTEXT about an upload) and `send(msg, to=addr)` route
  explicitly; `send(msg, broadcast=True)` goes to everyone (PARAM_VALUE after a PARAM_SET, so
  every ground station shows the value in force, as PX4 does).

Signing (MAVLink 2 message signing, optional): with a 32-byte secret key every outgoing packet is
signed (link_id, a timestamp in 10 µs units since 2015-01-01 that follows the wall clock and
never goes back, SHA-256 signature) and every incoming packet must carry a valid signature from
the same key with a timestamp that moves forward per (link_id, system, component) stream (a new
stream at most 60 s behind ours). Unsigned, wrongly signed and replayed packets are dropped and
counted (Parser.invalid: unsigned / bad_signature / replayed / stale_timestamp): they do not make
a ground station "alive", and get no reply. The key is never logged.

Ground stations. Only a HEARTBEAT from a ground station (MAV_TYPE_GCS, or a system id the
operator configured: `is_ground_station`) makes a peer a ground station (`ground_stations()`,
what gcs/link reports); any other heartbeat (a stray packet, a companion, another vehicle) only
makes its sender a telemetry destination.

Parsing is robust: garbage bytes, bad CRCs and unknown message ids are counted, never raised.
"""
from __future__ import annotations

import hashlib
import hmac
import os
import socket
import stat
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

from pymavlink.dialects.v20 import common as mavlink

MAX_DATAGRAM = 65535
MAX_PEERS = 16                      # addresses remembered (oldest forgotten first)
SIGNING_EPOCH_S = 1420070400        # 2015-01-01T00:00:00Z, the MAVLink signing epoch
SIGNING_KEY_LEN = 32
NEW_STREAM_WINDOW = 60 * 100_000    # a new signed stream may be this far (60 s) behind our timestamp
SIGNING_REJECTS = ("unsigned", "bad_signature", "replayed", "stale_timestamp")

Address = tuple[str, int]


def signing_timestamp(now_s: float | None = None) -> int:
    """MAVLink signing timestamp: 10 µs units since 2015-01-01 UTC."""
    t = time.time() if now_s is None else now_s
    return max(0, int((t - SIGNING_EPOCH_S) * 100_000))


def parse_signing_key(data: bytes | str) -> bytes:
    """64 hex digits (surrounding whitespace ignored) or exactly 32 raw bytes -> the 32-byte key.
    The error never quotes the content."""
    raw = data.encode("latin-1") if isinstance(data, str) else bytes(data)
    text = raw.strip()
    if len(text) == 2 * SIGNING_KEY_LEN:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(raw) == SIGNING_KEY_LEN:
        return raw
    raise ValueError(f"a MAVLink signing key is {2 * SIGNING_KEY_LEN} hex digits or {SIGNING_KEY_LEN} raw bytes "
                     f"(got {len(text)} characters that are neither)")


def load_signing_key(path: str | os.PathLike) -> tuple[bytes, bool]:
    """The key in a file (see parse_signing_key) and whether the file is readable by other users."""
    p = Path(path)
    try:
        data = p.read_bytes()
        mode = p.stat().st_mode
    except OSError as e:
        raise ValueError(f"signing key file {p}: {e.strerror}") from None
    try:
        key = parse_signing_key(data)
    except ValueError as e:
        raise ValueError(f"signing key file {p}: {e}") from None
    return key, bool(mode & (stat.S_IRWXG | stat.S_IRWXO))


class _MAVLink(mavlink.MAVLink):
    """pymavlink's MAVLink with a stricter signature check: the signature is verified before the
    timestamp is recorded, so a wrongly signed packet cannot move a stream's timestamp (pymavlink
    records it first), and the reason for a refusal is kept for the counters."""

    sig_failure = ""

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        sig = self.signing
        assert sig.secret_key is not None
        link_id = msgbuf[-13]
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = tlow + (thigh << 32)
        digest = hashlib.sha256(sig.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            self.sig_failure = "bad_signature"
            return False
        stream = (link_id, srcSystem, srcComponent)
        last = sig.stream_timestamps.get(stream)
        if last is not None and timestamp <= last:
            self.sig_failure = "replayed"
            return False
        if last is None and timestamp + NEW_STREAM_WINDOW < sig.timestamp:
            self.sig_failure = "stale_timestamp"
            return False
        sig.stream_timestamps[stream] = timestamp
        sig.timestamp = max(sig.timestamp, timestamp)
        return True


class _Writer:
    """pymavlink's MAVLink object writes encoded frames to `file.write` (unused: UdpLink packs)."""

    def __init__(self, link: "UdpLink"):
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link.send_bytes(bytes(buf))


def make_mav(system_id: int = 1, component_id: int = 1, file=None) -> mavlink.MAVLink:
    """A MAVLink 2 encoder/decoder with our identity."""
    mav = _MAVLink(file, srcSystem=system_id, srcComponent=component_id, use_native=False)
    mav.robust_parsing = True
    return mav


def _refuse_unsigned(_mav, _msg_id) -> bool:
    return False


class Parser:
    """Bytes -> MAVLink messages; invalid input is counted by reason, never raised."""

    def __init__(self, datagrams: bool = True, signing_key: bytes | None = None):
        self.datagrams = datagrams  # each feed() is one UDP datagram
        self.mav = make_mav()
        self.invalid: Counter[str] = Counter()
        self.received = 0
        self.signing = signing_key is not None
        if signing_key is not None:
            if len(signing_key) != SIGNING_KEY_LEN:
                raise ValueError(f"signing key must be {SIGNING_KEY_LEN} bytes")
            self.mav.signing.secret_key = bytes(signing_key)
            self.mav.signing.allow_unsigned_callback = _refuse_unsigned
            self.mav.signing.timestamp = signing_timestamp()

    def feed(self, data: bytes) -> list[mavlink.MAVLink_message]:
        out = []
        if self.signing:
            self.mav.signing.timestamp = max(self.mav.signing.timestamp, signing_timestamp())
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
                self.invalid[self._bad_reason(m)] += 1
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

    def _bad_reason(self, m) -> str:
        reason = str(getattr(m, "reason", "bad data")).lower()
        if "signature" in reason:
            frame = bytes(getattr(m, "data", b""))
            signed = (len(frame) > 2 and frame[0] == mavlink.PROTOCOL_MARKER_V2
                      and frame[2] & mavlink.MAVLINK_IFLAG_SIGNED)
            why = (getattr(self.mav, "sig_failure", "") or "bad_signature") if signed else "unsigned"
            self.mav.sig_failure = ""
            return why
        return "bad_crc" if "crc" in reason else "bad_data"

    @property
    def invalid_total(self) -> int:
        return sum(self.invalid.values())

    @property
    def signing_rejected(self) -> int:
        return sum(self.invalid[k] for k in SIGNING_REJECTS)


@dataclass
class Peer:
    """One ground station, by the address it sends from."""

    address: Address
    system_id: int = 0
    component_id: int = 0
    last_rx_s: float = 0.0
    last_heartbeat_s: float | None = None
    received: int = 0
    ground_station: bool = False     # its heartbeats say it is a ground station (see the module docstring)

    def alive(self, now_s: float, timeout_s: float) -> bool:
        return self.last_heartbeat_s is not None and now_s - self.last_heartbeat_s <= timeout_s


class UdpLink:
    """The socket, the ground stations heard, and the MAVLink encoder (thread-safe send)."""

    def __init__(self, bind_ip: str, local_port: int, gcs_ip: str, remote_port: int,
                 system_id: int = 1, component_id: int = 1, *, timeout_s: float = 3.5,
                 signing_key: bytes | None = None, signing_link_id: int = 0,
                 clock: Callable[[], float] = time.monotonic,
                 is_ground_station: Callable[[mavlink.MAVLink_message], bool] | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((bind_ip, local_port))
        self.sock.settimeout(0.2)
        self.local_address = self.sock.getsockname()
        self.initial: Address = (gcs_ip, remote_port)
        self.system_id = system_id
        self.component_id = component_id
        self.timeout_s = timeout_s
        self.clock = clock
        self.is_ground_station = is_ground_station or (lambda m: m.type == mavlink.MAV_TYPE_GCS)
        self.peers: OrderedDict[Address, Peer] = OrderedDict()   # least recently heard first
        self.by_id: OrderedDict[tuple[int, int], Address] = OrderedDict()
        self.last_peer: Address | None = None   # the latest HEARTBEAT's address
        self.learnt = False                     # any valid packet received
        self.mav = make_mav(system_id, component_id, _Writer(self))
        self.parser = Parser(signing_key=signing_key)
        self.signing = signing_key is not None
        if signing_key is not None:
            self.mav.signing.secret_key = bytes(signing_key)
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = int(signing_link_id) & 0xFF
            self.mav.signing.timestamp = signing_timestamp()
        self._lock = threading.RLock()
        self._ctx = threading.local()           # .source: the address of the message being handled
        self.sent = 0
        self.send_errors = 0
        self.datagrams = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def set_system_id(self, system_id: int) -> None:
        """Send as another system from now on (a companion follows its flight controller's id)."""
        with self._lock:
            self.system_id = system_id
            self.mav.srcSystem = system_id

    # ------------------------------------------------------------ peers

    @property
    def remote(self) -> Address:
        """The latest ground station heard (HEARTBEAT, else any packet), else the initial address."""
        with self._lock:
            if self.last_peer is not None:
                return self.last_peer
            if self.peers:
                return next(reversed(self.peers))
            return self.initial

    def alive(self, now_s: float | None = None) -> list[Peer]:
        """Ground stations with a HEARTBEAT within timeout_s, most recently heard last."""
        now = self.clock() if now_s is None else now_s
        with self._lock:
            return [p for p in self.peers.values() if p.alive(now, self.timeout_s)]

    def ground_stations(self, now_s: float | None = None) -> list[Peer]:
        """The alive peers whose heartbeats say they are ground stations."""
        return [p for p in self.alive(now_s) if p.ground_station]

    def destinations(self, now_s: float | None = None) -> list[Address]:
        """Where a message without a recipient goes (see the module docstring)."""
        alive = [p.address for p in self.alive(now_s)]
        if not alive and self.last_peer is not None:
            alive = [self.last_peer]
        return list(dict.fromkeys([self.initial] + alive))

    def current_source(self) -> Address | None:
        """The address of the message being handled on this thread (None outside a handler)."""
        return getattr(self._ctx, "source", None)

    def _note(self, msg, addr: Address, now: float) -> None:
        peer = self.peers.pop(addr, None) or Peer(addr)
        self.peers[addr] = peer                      # most recently heard last
        while len(self.peers) > MAX_PEERS:
            old, _ = self.peers.popitem(last=False)
            if self.last_peer == old:
                self.last_peer = None
        peer.last_rx_s = now
        peer.received += 1
        peer.system_id, peer.component_id = msg.get_srcSystem(), msg.get_srcComponent()
        ident = (peer.system_id, peer.component_id)
        self.by_id.pop(ident, None)
        self.by_id[ident] = addr
        while len(self.by_id) > 4 * MAX_PEERS:
            self.by_id.popitem(last=False)
        if msg.get_type() == "HEARTBEAT" and peer.system_id != self.system_id:
            peer.last_heartbeat_s = now
            peer.ground_station = bool(self.is_ground_station(msg))
            self.last_peer = addr
        self.learnt = True

    def _route(self, msg, to, peer, broadcast: bool) -> list[Address]:
        if to is not None:
            return [to] if isinstance(to, tuple) else list(to)
        if broadcast:
            return self.destinations()
        if peer is not None:
            addr = self.by_id.get(tuple(peer))
            if addr is not None:
                return [addr]
        src = self.current_source()
        if src is not None:
            return [src]
        target_sys = getattr(msg, "target_system", 0) or 0
        if target_sys:
            target_comp = getattr(msg, "target_component", 0) or 0
            addrs = [a for (s, c), a in self.by_id.items() if s == target_sys and (target_comp in (0, c))]
            if addrs:
                return list(dict.fromkeys(addrs))
        return self.destinations()

    # ------------------------------------------------------------ send

    def send_bytes(self, data: bytes, addresses: Iterable[Address] | None = None) -> None:
        for addr in (addresses if addresses is not None else self.destinations()):
            try:
                self.sock.sendto(data, addr)
                self.sent += 1
            except OSError:
                self.send_errors += 1

    def send(self, msg: mavlink.MAVLink_message, *, to: Address | Iterable[Address] | None = None,
             peer: tuple[int, int] | None = None, broadcast: bool = False) -> None:
        """Encode once (our sysid/compid, next sequence number, signed if signing) and send to
        the recipients chosen as the module docstring says."""
        with self._lock:
            addrs = self._route(msg, to, peer, broadcast)
            if self.signing:
                s = self.mav.signing
                s.timestamp = max(s.timestamp, self.parser.mav.signing.timestamp, signing_timestamp())
            buf = msg.pack(self.mav)
            self.mav.seq = (self.mav.seq + 1) % 256
            self.mav.total_packets_sent += 1
            self.send_bytes(buf, addrs)

    # ------------------------------------------------------------ receive

    def handle_datagram(self, data: bytes, addr: Address, now_s: float | None = None) -> list[mavlink.MAVLink_message]:
        now = self.clock() if now_s is None else now_s
        with self._lock:
            self.datagrams += 1
            msgs = self.parser.feed(data)
            for m in msgs:
                self._note(m, addr, now)   # only valid (and, with signing, correctly signed) packets
        return msgs

    def dispatch(self, data: bytes, addr: Address, on_message: Callable[[mavlink.MAVLink_message], None]) -> None:
        """Parse one datagram and hand each message to on_message, with replies routed to addr."""
        msgs = self.handle_datagram(data, addr)
        if not msgs:
            return
        self._ctx.source = addr
        try:
            for m in msgs:
                on_message(m)
        finally:
            self._ctx.source = None

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
                self.dispatch(data, addr, on_message)

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
