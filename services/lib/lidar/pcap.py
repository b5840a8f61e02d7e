"""The classic pcap file format (libpcap 2.4, both byte orders, micro- or nanosecond stamps) with
Ethernet II / 802.1Q / Linux cooked (SLL) / raw IPv4 link layers, IPv4 and UDP: what a LiDAR capture
made with tcpdump or Wireshark holds. Enough to replay a sensor's UDP stream; pcapng, IPv6 and IP
fragments are not read (they are skipped and counted, never a crash).
"""
from __future__ import annotations

import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

MAGIC_US = 0xA1B2C3D4
MAGIC_NS = 0xA1B23C4D
LINK_ETHERNET, LINK_RAW, LINK_IPV4, LINK_SLL = 1, 101, 228, 113
ETH_IPV4, ETH_VLAN = 0x0800, 0x8100
IP_UDP = 17


class PcapError(ValueError):
    """The file is not a classic pcap capture."""


@dataclass(frozen=True)
class UdpDatagram:
    stamp_ns: int            # capture time (the recording host's clock)
    src: tuple[str, int]     # (IPv4 address, port)
    dst: tuple[str, int]
    payload: bytes


@dataclass
class PcapStats:
    records: int = 0
    udp: int = 0
    skipped: Counter[str] = field(default_factory=Counter)   # reason -> records


def _ip(b: bytes) -> str:
    return ".".join(str(x) for x in b)


def read_udp(path: str | Path, stats: PcapStats | None = None) -> Iterator[UdpDatagram]:
    """Every UDP datagram of a capture, in file order. A record cut short at the end of the file
    ends the iteration; records that are not UDP over IPv4 are counted in `stats.skipped`."""
    st = stats if stats is not None else PcapStats()
    with open(path, "rb") as f:
        yield from _read(f, st)


def _read(f: BinaryIO, st: PcapStats) -> Iterator[UdpDatagram]:
    head = f.read(24)
    if len(head) < 24:
        raise PcapError(f"{len(head)} bytes is too short for a pcap header")
    for endian in ("<", ">"):
        magic = struct.unpack(endian + "I", head[:4])[0]
        if magic in (MAGIC_US, MAGIC_NS):
            break
    else:
        raise PcapError(f"magic {head[:4].hex()} is not classic pcap (pcapng? convert with `editcap -F pcap`)")
    frac_ns = 1 if magic == MAGIC_NS else 1000
    link = struct.unpack(endian + "I", head[20:24])[0] & 0x0FFFFFFF
    rec = struct.Struct(endian + "IIII")
    while True:
        rh = f.read(16)
        if len(rh) < 16:
            return
        sec, frac, incl, _orig = rec.unpack(rh)
        data = f.read(incl)
        if len(data) < incl:
            st.skipped["truncated record at end of file"] += 1
            return
        st.records += 1
        d = _udp(data, link, st)
        if d is not None:
            st.udp += 1
            yield UdpDatagram(sec * 1_000_000_000 + frac * frac_ns, *d)


def _udp(data: bytes, link: int, st: PcapStats) -> tuple[tuple[str, int], tuple[str, int], bytes] | None:
    if link == LINK_ETHERNET:
        off, ethertype = 14, int.from_bytes(data[12:14], "big") if len(data) >= 14 else 0
        while ethertype == ETH_VLAN and len(data) >= off + 4:
            ethertype, off = int.from_bytes(data[off + 2:off + 4], "big"), off + 4
    elif link == LINK_SLL:
        off, ethertype = 16, int.from_bytes(data[14:16], "big") if len(data) >= 16 else 0
    elif link in (LINK_RAW, LINK_IPV4):
        off, ethertype = 0, ETH_IPV4
    else:
        st.skipped[f"link type {link}"] += 1
        return None
    if ethertype != ETH_IPV4 or len(data) < off + 20 or data[off] >> 4 != 4:
        st.skipped["not IPv4"] += 1
        return None
    ihl = (data[off] & 0x0F) * 4
    total = int.from_bytes(data[off + 2:off + 4], "big")
    frag = int.from_bytes(data[off + 6:off + 8], "big")
    if data[off + 9] != IP_UDP:
        st.skipped["not UDP"] += 1
        return None
    if frag & 0x3FFF:             # more-fragments flag or an offset
        st.skipped["IP fragment"] += 1
        return None
    u = off + ihl
    end = min(len(data), off + total) if total else len(data)
    if end < u + 8:
        st.skipped["truncated UDP header"] += 1
        return None
    sport, dport, ulen = struct.unpack(">HHH", data[u:u + 6])
    if ulen < 8 or u + ulen > end:
        st.skipped["truncated UDP payload"] += 1
        return None
    src = (_ip(data[off + 12:off + 16]), sport)
    dst = (_ip(data[off + 16:off + 20]), dport)
    return src, dst, bytes(data[u + 8:u + ulen])
