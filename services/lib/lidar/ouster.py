"""Ouster lidar and IMU packets (OS-0/1/2, firmware 2.x), laid out by the sensor's metadata JSON, per
Ouster's sensor documentation ("Lidar data packet format", "Coordinate frames"); no ouster-sdk.

A lidar packet is a 32-byte header (packet type, frame id, ...), `columns_per_packet` columns and a
32-byte footer (the LEGACY profile: no header/footer, a 16-byte column header and a 4-byte status
word after each column). A column: a 12-byte header (timestamp ns, measurement id = the encoder
column 0..columns_per_frame-1, status with bit 0 = valid), then `pixels_per_column` pixels in the
profile's layout. Pixels are "staggered": row i of a column is the beam i fired at that encoder
angle; `destagger` shifts each row by pixel_shift_by_row to make the image a camera would see.

Points: the sensor frame (x forward, z up, metres), from the beam intrinsics:
  theta_e = 2 pi (1 - measurement_id / columns_per_frame), theta_a = -2 pi beam_azimuth / 360,
  phi = 2 pi beam_altitude / 360, n = lidar_origin_to_beam_origin_mm,
  lidar frame: ((r - n) cos(theta_e + theta_a) cos(phi) + n cos(theta_e),
                (r - n) sin(theta_e + theta_a) cos(phi) + n sin(theta_e), (r - n) sin(phi) + beam z),
then lidar_to_sensor_transform (mm). A packet that cannot be decoded raises PacketError.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .velodyne import PacketError

# profile -> (bytes per pixel, (field, byte offset, dtype, bit mask, scale))
PROFILES: dict[str, tuple[int, tuple[tuple[str, int, str, int, float], ...]]] = {
    "LEGACY": (12, (("range_mm", 0, "<u4", 0xFFFFF, 1.0), ("reflectivity", 4, "<u2", 0xFFFF, 1.0),
                    ("signal", 6, "<u2", 0xFFFF, 1.0), ("nir", 8, "<u2", 0xFFFF, 1.0))),
    "RNG19_RFL8_SIG16_NIR16": (12, (("range_mm", 0, "<u4", 0x7FFFF, 1.0), ("reflectivity", 4, "u1", 0xFF, 1.0),
                                    ("signal", 6, "<u2", 0xFFFF, 1.0), ("nir", 8, "<u2", 0xFFFF, 1.0))),
    "RNG15_RFL8_NIR8": (4, (("range_mm", 0, "<u2", 0x7FFF, 8.0), ("reflectivity", 2, "u1", 0xFF, 1.0),
                            ("nir", 3, "u1", 0xFF, 1.0))),
}
IMU_PACKET_BYTES = 48


@dataclass(frozen=True)
class OusterMetadata:
    columns_per_frame: int
    columns_per_packet: int
    pixels_per_column: int
    pixel_shift_by_row: np.ndarray          # (H,) int
    profile: str
    direction: np.ndarray                   # (H, W, 3): unit vector per pixel, sensor frame
    offset_m: np.ndarray                    # (H, W, 3): beam origin per pixel, sensor frame
    lidar_port: int
    imu_port: int
    ring: np.ndarray                        # (H,) uint16 per row: 0 = the lowest beam
    imu_to_sensor: np.ndarray = field(default_factory=lambda: np.eye(4))   # 4x4, metres: sensor <- IMU

    @classmethod
    def load(cls, path: str | Path) -> "OusterMetadata":
        return cls.from_json(json.loads(Path(path).read_text()))

    @classmethod
    def from_json(cls, m: dict[str, Any]) -> "OusterMetadata":
        fmt = m["data_format"]
        profile = fmt.get("udp_profile_lidar", "LEGACY")
        if profile not in PROFILES:
            raise ValueError(f"lidar profile {profile!r} not supported; supported: {', '.join(PROFILES)}")
        w, h = int(fmt["columns_per_frame"]), int(fmt["pixels_per_column"])
        alt = np.radians(np.asarray(m["beam_altitude_angles"], float))[:, None]
        azi = -np.radians(np.asarray(m["beam_azimuth_angles"], float))[:, None]
        if "beam_to_lidar_transform" in m:
            b = np.asarray(m["beam_to_lidar_transform"], float).reshape(4, 4)
            n_mm, z_mm = float(np.hypot(b[0, 3], b[2, 3])), float(b[2, 3])
        else:
            n_mm, z_mm = float(m["lidar_origin_to_beam_origin_mm"]), 0.0
        enc = 2.0 * np.pi * (1.0 - np.arange(w) / w)[None, :]
        d = np.stack([np.cos(enc + azi) * np.cos(alt), np.sin(enc + azi) * np.cos(alt),
                      np.broadcast_to(np.sin(alt), (h, w))], axis=-1)
        o = np.stack([n_mm * np.cos(enc) - n_mm * d[..., 0], n_mm * np.sin(enc) - n_mm * d[..., 1],
                      np.full((h, w), z_mm) - n_mm * d[..., 2]], axis=-1) * 1e-3
        t = np.asarray(m.get("lidar_to_sensor_transform", np.eye(4).ravel()), float).reshape(4, 4)
        return cls(w, int(fmt["columns_per_packet"]), h, np.asarray(fmt["pixel_shift_by_row"], int), profile,
                   d @ t[:3, :3].T, o @ t[:3, :3].T + t[:3, 3] * 1e-3,
                   int(m.get("udp_port_lidar", 7502)), int(m.get("udp_port_imu", 7503)),
                   np.argsort(np.argsort(alt[:, 0], kind="stable"), kind="stable").astype(np.uint16),
                   _mm_to_m(m.get("imu_to_sensor_transform")))

    @property
    def legacy(self) -> bool:
        return self.profile == "LEGACY"

    @property
    def packet_bytes(self) -> int:
        col = self.pixels_per_column * PROFILES[self.profile][0] + (20 if self.legacy else 12)
        return self.columns_per_packet * col + (0 if self.legacy else 64)


@dataclass(frozen=True)
class OusterColumns:
    """One lidar packet: per column its stamp, encoder column and validity; per pixel the fields."""
    frame_id: int
    stamp_ns: np.ndarray            # (C,) uint64
    measurement_id: np.ndarray      # (C,) int: column in the frame
    valid: np.ndarray               # (C,) bool
    fields: dict[str, np.ndarray]   # name -> (C, H)


def decode_lidar(meta: OusterMetadata, packet: bytes) -> OusterColumns:
    if len(packet) != meta.packet_bytes:
        raise PacketError(f"{len(packet)} bytes, a {meta.profile} lidar packet has {meta.packet_bytes}")
    px_bytes, layout = PROFILES[meta.profile]
    c, h = meta.columns_per_packet, meta.pixels_per_column
    head = 16 if meta.legacy else 12
    col_bytes = head + h * px_bytes + (4 if meta.legacy else 0)
    start = 0 if meta.legacy else 32
    cols = np.frombuffer(packet, np.uint8, count=c * col_bytes, offset=start).reshape(c, col_bytes)
    stamp = cols[:, 0:8].copy().view("<u8")[:, 0]
    mid = cols[:, 8:10].copy().view("<u2")[:, 0].astype(np.intp)
    if meta.legacy:
        frame_id = int(cols[0, 10:12].copy().view("<u2")[0])
        valid = cols[:, -4:].copy().view("<u4")[:, 0] == 0xFFFFFFFF
    else:
        frame_id = int.from_bytes(packet[2:4], "little")
        valid = (cols[:, 10:12].copy().view("<u2")[:, 0] & 1) == 1
    if np.any(mid >= meta.columns_per_frame):
        raise PacketError(f"measurement id {int(mid.max())} beyond {meta.columns_per_frame} columns")
    px = cols[:, head:head + h * px_bytes].reshape(c, h, px_bytes)
    fields = {}
    for name, off, dt, mask, scale in layout:
        size = np.dtype(dt).itemsize
        raw = px[:, :, off:off + size].copy().view(dt)[..., 0].astype(np.uint32) & mask
        fields[name] = raw * scale if scale != 1.0 else raw
    return OusterColumns(frame_id, stamp, mid, valid, fields)


def xyz(meta: OusterMetadata, range_mm: np.ndarray, measurement_id: np.ndarray | None = None) -> np.ndarray:
    """Points (..., H, C, 3) in metres for a staggered range image (H, C) whose columns are the
    frame's `measurement_id` (all columns in order when None); range 0 (no return) gives 0, 0, 0."""
    cols = slice(None) if measurement_id is None else measurement_id
    r = np.asarray(range_mm, float)[..., None] * 1e-3
    return np.where(r > 0, r * meta.direction[:, cols] + meta.offset_m[:, cols], 0.0)


def destagger(meta: OusterMetadata, image: np.ndarray) -> np.ndarray:
    """A staggered (H, W) field as the sensor's view: row i rolled by pixel_shift_by_row[i]."""
    out = np.empty_like(image)
    for i, s in enumerate(meta.pixel_shift_by_row):
        out[i] = np.roll(image[i], int(s))
    return out


@dataclass(frozen=True)
class OusterImu:
    sys_stamp_ns: int
    accel_stamp_ns: int
    gyro_stamp_ns: int
    accel_g: np.ndarray           # (3,) in g, the IMU frame
    gyro_dps: np.ndarray          # (3,) deg/s


def _mm_to_m(t: Any) -> np.ndarray:
    """A metadata 4x4 transform (row-major, translation in mm) with its translation in metres."""
    out = np.asarray(t if t is not None else np.eye(4).ravel(), float).reshape(4, 4).copy()
    out[:3, 3] *= 1e-3
    return out


def decode_imu(packet: bytes) -> OusterImu:
    if len(packet) != IMU_PACKET_BYTES:
        raise PacketError(f"{len(packet)} bytes, an IMU packet has {IMU_PACKET_BYTES}")
    t = np.frombuffer(packet, "<u8", count=3)
    v = np.frombuffer(packet, "<f4", count=6, offset=24).astype(float)
    return OusterImu(int(t[0]), int(t[1]), int(t[2]), v[:3], v[3:])
