"""Packets into whole rotations, free of sockets and Zenoh: feed (payload, arrival ns), get the
scans a rotation completed, and the counters diagnostics report.

A Velodyne rotation ends where the azimuth wraps (points before 180 deg of the wrap packet go to
the new scan); an Ouster rotation is one frame id. Coverage is the share of the rotation that
arrived (1-degree azimuth bins, or the frame's columns): below min_coverage the scan is dropped
with its reason, else published with what arrived.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from aeroperception.services.lib.lidar import ouster, velodyne
from aeroperception.services.lib.lidar.velodyne import PacketError
from aeroperception.services.runtime.config import param

HOUR_NS = 3600 * 1_000_000_000
# A packet at most this many rotations earlier than the one before it arrived out of order (it is
# dropped); farther back, the sensor's clock jumped back (re-sync, reboot) and the stream restarts.
REORDER_ROTATIONS = 2
G_MPS2 = 9.80665                 # the g an Ouster IMU reports accelerations in
REORDER_FRAMES = 1


@dataclass(frozen=True)
class DriverConfig:
    vendor: str = param("vendor")
    model: str = param("model")
    metadata_path: str = param("metadata_path")
    device_ip: str = param("device_ip")
    bind_address: str = param("bind_address")
    port: int = param("port")
    imu_port: int = param("imu_port")
    frame_id: str = param("frame_id")
    scan_rate_hz: float = param("scan_rate_hz")
    min_range_m: float = param("min_range_m")
    max_range_m: float = param("max_range_m")
    expected_points: int = param("expected_points")
    min_coverage: float = param("min_coverage")
    time_source: str = param("time_source")


@dataclass
class ImuSample:
    """One Ouster IMU packet in the sensor frame, SI units."""
    stamp_ns: int
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray


@dataclass
class Scan:
    stamp_ns: int                  # the first point's time
    xyz_m: np.ndarray              # (N, 3) float32, sensor frame
    intensity: np.ndarray          # (N,) float32
    ring: np.ndarray               # (N,) uint16
    time_offset_s: np.ndarray      # (N,) float32 after stamp_ns
    coverage: float                # share of the rotation that arrived
    packets: int


@dataclass
class _Batch:
    """One packet's points: absolute times, and where in the rotation they lie."""
    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    t_ns: np.ndarray
    cells: np.ndarray              # coverage cells hit: per point its azimuth degree (Velodyne), or the columns (Ouster)
    new_scan: np.ndarray | None    # per point: belongs to the next rotation (Velodyne wrap)
    frame: int | None              # Ouster frame id
    restarted: bool = False        # the sensor's clock jumped back before this packet (Velodyne)


@dataclass
class ScanAssembler:
    cfg: DriverConfig
    counts: Counter[str] = field(default_factory=Counter)
    last_scan: Scan | None = None

    def __post_init__(self) -> None:
        if self.cfg.imu_port and self.cfg.vendor != "ouster":
            raise ValueError(f"imu_port {self.cfg.imu_port}: only an Ouster sends IMU packets (vendor is "
                             f"{self.cfg.vendor}): it would never be read")
        if self.cfg.vendor == "ouster":
            if not self.cfg.metadata_path:
                raise ValueError("vendor ouster needs metadata_path (the sensor's metadata JSON)")
            self.meta: ouster.OusterMetadata | None = ouster.OusterMetadata.load(self.cfg.metadata_path)
            self.velodyne: velodyne.VelodyneDecoder | None = None
            self.cells_per_rotation = self.meta.columns_per_frame
        else:
            self.meta = None
            self.velodyne = velodyne.VelodyneDecoder(None if self.cfg.model == "auto" else self.cfg.model)
            self.cells_per_rotation = 360
        self._parts: list[_Batch] = []
        self._cover = np.zeros(self.cells_per_rotation, bool)   # which cells of the rotation arrived
        self._frame: int | None = None
        self._last_az: float | None = None
        self._last_dev: int | None = None      # the previous packet's sensor time (ns)
        self._last_rx_ns = 0

    # ------------------------------------------------------------ packets in

    def feed(self, payload: bytes, rx_ns: int) -> list[Scan]:
        return self.feed_many([(payload, rx_ns)])

    def feed_many(self, packets: list[tuple[bytes, int]]) -> list[Scan]:
        """(payload, arrival ns) in arrival order -> the scans they complete. A burst read from the
        socket at once is decoded in one batch (VelodyneDecoder.decode_many): the same result as
        feeding the packets one by one, at a fraction of the CPU."""
        decoded: list = [None] * len(packets)
        if self.velodyne is not None:
            data = [i for i, (pk, _) in enumerate(packets) if len(pk) != 512]
            for i, res in zip(data, self.velodyne.decode_many([packets[i][0] for i in data])):
                decoded[i] = res
        out: list[Scan] = []
        for (payload, rx_ns), pre in zip(packets, decoded):
            out += self._feed_one(payload, rx_ns, pre)
        return out

    def _feed_one(self, payload: bytes, rx_ns: int, pre) -> list[Scan]:
        self.counts["packets"] += 1
        try:
            if isinstance(pre, PacketError):
                raise pre
            b = self._ouster(payload, rx_ns) if self.meta is not None else self._velodyne(payload, rx_ns, pre)
        except PacketError as e:
            self.counts[f"bad: {e}".split(",")[0][:60]] += 1
            self.counts["bad_packets"] += 1
            return []
        if b is None:
            return []
        self._last_rx_ns = rx_ns
        out: list[Scan] = []
        if b.frame is not None:                        # Ouster: one frame id per rotation
            if self._frame is not None and b.frame != self._frame:
                back = (self._frame - b.frame) % 65536
                if back <= REORDER_FRAMES:
                    self.counts["reordered_packets"] += 1
                    return []
                if back < 32768:                       # far back: the sensor restarted (frame ids anew)
                    self.counts["clock_jumps"] += 1
                    out += self._finish("sensor restarted")
                else:
                    out += self._finish("frame ended")
            self._frame = b.frame
            self._add(b, None)
        else:
            if b.restarted:
                out += self._finish("sensor clock jumped back")
            split = b.new_scan
            if split is not None and split.any():
                self._add(b, ~split)
                out += self._finish("rotation ended")
                self._add(b, split)
            else:
                self._add(b, None)
        return out

    def flush(self, now_ns: int) -> list[Scan]:
        """No packet for two rotation periods: end the scan in progress (a stalled or stopped sensor)."""
        if self._parts and now_ns - self._last_rx_ns > 2e9 / self.cfg.scan_rate_hz:
            self._last_az, self._last_dev = None, None
            return self._finish("stream stalled")
        return []

    def _add(self, b: _Batch, keep: np.ndarray | None) -> None:
        if keep is not None:
            b = _Batch(b.xyz[keep], b.intensity[keep], b.ring[keep], b.t_ns[keep],
                       b.cells[keep] if b.frame is None else b.cells, None, b.frame)
        self._parts.append(b)
        self._cover[b.cells] = True

    def _finish(self, why: str) -> list[Scan]:
        parts, cells = self._parts, int(self._cover.sum())
        self._parts = []
        self._cover[:] = False
        if not parts:
            return []
        coverage = cells / self.cells_per_rotation
        if self.meta is not None:
            self.counts["lost_columns"] += self.cells_per_rotation - cells
        if coverage < self.cfg.min_coverage:
            self.counts[f"scans_dropped: {coverage:.0%} of the rotation ({why})"] += 1
            self.counts["scans_dropped"] += 1
            return []
        xyz = np.concatenate([p.xyz for p in parts])
        r = np.linalg.norm(xyz, axis=1)
        keep = (r >= self.cfg.min_range_m) & (r <= self.cfg.max_range_m)
        t = np.concatenate([p.t_ns for p in parts])[keep]
        stamp = int(t.min()) if t.size else int(parts[0].t_ns.min()) if parts[0].t_ns.size else self._last_rx_ns
        scan = Scan(stamp, xyz[keep].astype(np.float32), np.concatenate([p.intensity for p in parts])[keep].astype(np.float32),
                    np.concatenate([p.ring for p in parts])[keep].astype(np.uint16),
                    ((t - stamp) * 1e-9).astype(np.float32), coverage, len(parts))
        self.counts["scans"] += 1
        self.last_scan = scan
        return [scan]

    def imu(self, payload: bytes, rx_ns: int) -> ImuSample | None:
        """An Ouster IMU packet (imu_port) in the sensor frame: accelerations g -> m/s^2, rates
        deg/s -> rad/s, rotated by the metadata's imu_to_sensor_transform; stamped like the scans
        (the accelerometer's sensor time, or the arrival). None, counted, when it does not decode."""
        self.counts["imu_packets"] += 1
        if self.meta is None:
            self.counts["bad_imu_packets"] += 1
            return None
        try:
            m = ouster.decode_imu(payload)
        except PacketError as e:
            self.counts[f"bad imu: {e}"[:60]] += 1
            self.counts["bad_imu_packets"] += 1
            return None
        r = self.meta.imu_to_sensor[:3, :3]
        stamp = m.accel_stamp_ns if self.cfg.time_source == "sensor" else rx_ns
        return ImuSample(stamp, r @ np.radians(m.gyro_dps), r @ (m.accel_g * G_MPS2))

    # ------------------------------------------------------------ vendors

    def _velodyne(self, payload: bytes, rx_ns: int, p: velodyne.VelodynePoints | None) -> _Batch | None:
        assert self.velodyne is not None
        if len(payload) == 512:          # position (GPS/NMEA) packets share the stream on some setups
            self.counts["position_packets"] += 1
            return None
        assert p is not None
        dev_ns = p.stamp_us * 1000
        restarted = False
        if self._last_dev is not None:
            gap = (dev_ns - self._last_dev) % HOUR_NS
            if gap > HOUR_NS // 2 and HOUR_NS - gap <= REORDER_ROTATIONS * 1e9 / self.cfg.scan_rate_hz:
                self.counts["reordered_packets"] += 1  # a little earlier than the previous packet
                return None
            if gap > HOUR_NS // 2:
                # far earlier: the sensor's clock jumped back (a GPS/PTP re-sync, a reboot, a replay
                # started over): the scan in progress ends and the stream is taken from here
                self.counts["clock_jumps"] += 1
                restarted, self._last_az = True, None
            else:
                m = self.velodyne.model_of(payload)  # a packet spans 12 blocks (6 in dual mode) of firings
                blocks = velodyne.BLOCKS // (2 if p.return_mode == "dual" else 1)
                period = m.firing_period_us * 1000 * (velodyne.SLOTS // m.lasers) * blocks
                if gap > 1.5 * period:
                    self.counts["lost_packets"] += int(round(gap / period)) - 1
        self._last_dev = dev_ns
        t_off = (p.time_offset_s * 1e9).astype(np.int64)
        if self.cfg.time_source == "sensor":        # the hour from our clock, nearest to the arrival
            base = rx_ns - rx_ns % HOUR_NS + dev_ns
            base += HOUR_NS * int(np.round((rx_ns - base) / HOUR_NS))
        else:                                       # arrival = just after the packet's last firing
            base = rx_ns - int(t_off.max() if t_off.size else 0)
        az = p.azimuth_deg
        new_scan = None
        if az.size:
            wrapped_inside = az.max() - az.min() > 180.0
            wrapped_before = self._last_az is not None and self._last_az - float(az[0]) > 180.0
            if wrapped_inside:
                new_scan = az < 180.0
            elif wrapped_before:
                new_scan = np.ones(az.size, bool)
            self._last_az = float(az[-1])
        return _Batch(p.xyz_m, p.reflectivity.astype(np.float32), p.ring, base + t_off,
                      np.floor(az).astype(np.int64) % 360, new_scan, None, restarted)

    def _ouster(self, payload: bytes, rx_ns: int) -> _Batch | None:
        meta = self.meta
        assert meta is not None
        if len(payload) == ouster.IMU_PACKET_BYTES:    # sent to the lidar port too: read on imu_port
            self.counts["imu_packets_on_lidar_port"] += 1
            return None
        c = ouster.decode_lidar(meta, payload)
        self.counts["invalid_columns"] += int((~c.valid).sum())
        cols = c.measurement_id[c.valid]
        rng = c.fields["range_mm"][c.valid].T                      # (H, C)
        pts = ouster.xyz(meta, rng, cols)                          # (H, C, 3)
        hit = rng > 0
        stamps = c.stamp_ns[c.valid].astype(np.int64)
        if self.cfg.time_source == "sensor":
            t_col = stamps
        else:
            t_col = rx_ns - (int(stamps.max()) - stamps) if stamps.size else stamps
        ring = np.broadcast_to(meta.ring[:, None], hit.shape)
        refl = c.fields["reflectivity"][c.valid].T.astype(np.float32)
        return _Batch(pts[hit], refl[hit], ring[hit], np.broadcast_to(t_col[None, :], hit.shape)[hit], cols,
                      None, c.frame_id)
