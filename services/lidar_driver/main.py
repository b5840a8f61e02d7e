"""Process shell: a UDP socket's packets into the ScanAssembler, its scans onto Zenoh."""
from __future__ import annotations

import socket
import threading
import time

from aeroperception.schemas import DiagnosticStatus, Header, NDArray, PointCloud
from aeroperception.services.runtime import Health, Service, run

from . import contract
from .logic import DriverConfig, Scan, ScanAssembler


# Datagrams read in one go after the first: a VLP-16 sends 754 a second, so this is ~85 ms of
# backlog at most, decoded together (ScanAssembler.feed_many).
MAX_BURST = 64


class LidarDriverService(Service):
    """Velodyne / Ouster packets in, whole rotations on sensors/lidar/points."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = DriverConfig

    def start(self) -> None:
        p = self.cfg
        self.assembler = ScanAssembler(self.cfg)
        self.pub = self.io["sensors/lidar/points"]
        self.device_ip = p.device_ip
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind((p.bind_address, p.port))
        self.sock.settimeout(0.1)
        self.wrong_source = 0
        self.reader = threading.Thread(target=self._read_loop, name="lidar-udp", daemon=True)
        self.reader.start()
        self.log.info("listening", address=p.bind_address, port=p.port, vendor=self.cfg.vendor,
                      device_ip=self.device_ip or "any")

    def on_config(self, cfg: DriverConfig) -> None:
        self.assembler.cfg = cfg

    def stop(self) -> None:
        self.node.stop_event.set()
        if hasattr(self, "reader"):
            self.reader.join(1.0)
        if hasattr(self, "sock"):
            self.sock.close()

    def _read_loop(self) -> None:
        while not self.node.stop_event.is_set():
            try:
                payload, (ip, _port) = self.sock.recvfrom(65535)
            except TimeoutError:
                self.node.run_callback("lidar-udp", self._flush)
                continue
            except OSError as e:
                self.log.throttled("warn", "udp", "udp_read_error", error=str(e))
                time.sleep(0.05)
                continue
            burst = [(payload, ip, time.time_ns())]
            # what else is already queued (a burst behind a slow decode): decoded as one batch
            while len(burst) < MAX_BURST:
                try:
                    payload, (ip, _port) = self.sock.recvfrom(65535, socket.MSG_DONTWAIT)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    break
                burst.append((payload, ip, time.time_ns()))
            packets = []
            for payload, ip, rx_ns in burst:
                if self.device_ip and ip != self.device_ip:
                    self.wrong_source += 1
                    self.node.report_bad_input("udp", f"packet from {ip}, expected device_ip {self.device_ip}")
                else:
                    packets.append((payload, rx_ns))
            if packets:
                self.node.run_callback("lidar-udp", self._on_packets, packets)

    def _on_packets(self, packets: list[tuple[bytes, int]]) -> None:
        for scan in self.assembler.feed_many(packets):
            self._publish(scan)

    def _flush(self) -> None:
        for scan in self.assembler.flush(time.time_ns()):
            self._publish(scan)

    def _publish(self, scan: Scan) -> None:
        self.pub.publish(PointCloud(
            header=Header(stamp_ns=scan.stamp_ns, frame_id=self.cfg.frame_id),
            points=NDArray.from_numpy(scan.xyz_m), intensity=NDArray.from_numpy(scan.intensity),
            ring=NDArray.from_numpy(scan.ring), time_offset_s=NDArray.from_numpy(scan.time_offset_s)))

    def health(self) -> Health:
        c = self.assembler.counts
        last = self.assembler.last_scan
        values = {k: v for k, v in sorted(c.items())} | {"wrong_source_packets": self.wrong_source}
        if last is not None:
            values |= {"last_points": len(last.xyz_m), "last_coverage": round(last.coverage, 3)}
        if last is None:
            return Health(DiagnosticStatus.WARN, "no scan yet", values)
        if len(last.xyz_m) < self.cfg.expected_points / 2:
            return Health(DiagnosticStatus.WARN, f"last scan {len(last.xyz_m)} points, expected ~"
                          f"{self.cfg.expected_points}", values)
        return Health(DiagnosticStatus.OK, f"{c['scans']} scans, {c['bad_packets']} bad packets", values)


def main(argv=None) -> int:
    return run(LidarDriverService, argv)
