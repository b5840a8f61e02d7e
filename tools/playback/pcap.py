"""A LiDAR packet capture as the UDP datagrams the sensor sent, at their capture timing: what
`aero play pcap FILE` sends to a lidar_driver (the sensor on the vehicle's network, without it).

Each datagram keeps its captured destination port (an Ouster's lidar 7502 and IMU 7503, a
Velodyne's data 2368 and position 8308 stay apart) unless moved: one port for all, or per port.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from aeroperception.services.lib.lidar.pcap import PcapError, PcapStats, read_udp
from aeroperception.services.recorder.replay import Recorded

from .euroc import PlaybackError, Window

UDP_PREFIX = "udp/"


def datagrams(path: str | Path, window: Window = Window(), ports: dict[int | None, int] | None = None,
              stats: PcapStats | None = None) -> Iterator[Recorded]:
    """The capture's UDP payloads in the window as Recorded("udp/<port>", "", payload, capture time);
    `ports` {captured: sent to} (key None: every datagram) moves them to other ports."""
    ports = ports or {}
    stats = stats if stats is not None else PcapStats()
    t0 = None
    try:
        for d in read_udp(path, stats):
            if t0 is None:
                t0 = d.stamp_ns
            rel_s = (d.stamp_ns - t0) * 1e-9
            if rel_s < window.start_s:
                continue
            if window.duration_s is not None and rel_s > window.start_s + window.duration_s:
                break
            port = ports.get(None) or ports.get(d.dst[1]) or d.dst[1]
            yield Recorded(f"{UDP_PREFIX}{port}", "", d.payload, d.stamp_ns)
    except (PcapError, OSError) as e:
        raise PlaybackError(f"{path}: {e}") from None
    if t0 is None:
        raise PlaybackError(f"{path}: no UDP datagram in the capture ({dict(stats.skipped) or 'empty'})")
