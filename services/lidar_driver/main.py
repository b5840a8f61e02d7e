"""Process shell: a UDP socket's packets into the ScanAssembler, its scans onto Zenoh."""
from __future__ import annotations

import select
import socket
import threading
import time

from aeroperception.schemas import DiagnosticStatus, Header, Imu, NDArray, PointCloud, Vector3
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

    def bind_selection(self) -> dict:
        """sensors/lidar/imu only when the IMU packets are read (an Ouster with imu_port)."""
        return dict(outputs=["sensors/lidar/points"] + (["sensors/lidar/imu"] if self.cfg.imu_port else []))

    def start(self) -> None:
        p = self.cfg
        self.assembler = ScanAssembler(self.cfg)
        self.pub = self.io["sensors/lidar/points"]
        self.device_ip = p.device_ip
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind((p.bind_address, p.port))
        self.sock.setblocking(False)
        self.imu_sock: socket.socket | None = None
        if p.imu_port:
            self.imu_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.imu_sock.bind((p.bind_address, p.imu_port))
            self.imu_sock.setblocking(False)
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
        if getattr(self, "imu_sock", None) is not None:
            self.imu_sock.close()

    def _read_loop(self) -> None:
        socks = [self.sock] + ([self.imu_sock] if self.imu_sock is not None else [])
        while not self.node.stop_event.is_set():
            try:
                ready, _, _ = select.select(socks, [], [], 0.1)
            except (OSError, ValueError) as e:         # a socket closed under us: stopping
                self.log.throttled("warn", "udp", "udp_read_error", error=str(e))
                time.sleep(0.05)
                continue
            if not ready:
                self.node.run_callback("lidar-udp", self._flush)
                continue
            if self.imu_sock is not None and self.imu_sock in ready:
                for payload, rx_ns in self._drain(self.imu_sock):
                    self.node.run_callback("lidar-imu", self._on_imu_packet, payload, rx_ns)
            if self.sock in ready:
                packets = self._drain(self.sock)
                if packets:
                    self.node.run_callback("lidar-udp", self._on_packets, packets)

    def _drain(self, sock: socket.socket) -> list[tuple[bytes, int]]:
        """Everything the socket holds now (up to MAX_BURST), from the expected device only."""
        out: list[tuple[bytes, int]] = []
        while len(out) < MAX_BURST:
            try:
                payload, (ip, _port) = sock.recvfrom(65535, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as e:
                self.log.throttled("warn", "udp", "udp_read_error", error=str(e))
                break
            if self.device_ip and ip != self.device_ip:
                self.wrong_source += 1
                self.node.report_bad_input("udp", f"packet from {ip}, expected device_ip {self.device_ip}")
                continue
            out.append((payload, time.time_ns()))
        return out

    def _on_imu_packet(self, payload: bytes, rx_ns: int) -> None:
        s = self.assembler.imu(payload, rx_ns)
        if s is not None:
            self.io["sensors/lidar/imu"].publish(Imu(
                header=Header(stamp_ns=s.stamp_ns, frame_id=self.cfg.frame_id),
                angular_velocity_radps=Vector3.from_array(s.gyro_radps),
                linear_acceleration_mps2=Vector3.from_array(s.accel_mps2)))

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
