"""Velodyne data packets (VLP-16 / Puck, VLP-32C, HDL-32E) decoded into points, per the user
manuals' packet layout, calibration tables and firing timing tables.

A data packet is 1206 bytes: 12 blocks of 100 bytes (flag 0xFFEE, azimuth in 0.01 deg, 32 x
(distance uint16 in the model's unit, reflectivity uint8)), a uint32 timestamp (us past the hour
of the first firing of the first block), and two factory bytes: the return mode (0x37 strongest,
0x38 last, 0x39 dual) and the product id (0x21 HDL-32E, 0x22 VLP-16, 0x24 Puck Hi-Res, 0x28
VLP-32C). A VLP-16 block holds two firing sequences of 16 channels; in dual mode blocks come in
pairs of one firing (even: last return, odd: strongest, or the second strongest when the two are
the same return).

Points are in the sensor frame as ROS and the reference decoders give it (x forward through the
azimuth 0 direction, y left, z up): x = r cos(el) cos(az), y = -r cos(el) sin(az), z = r sin(el),
azimuth measured clockwise seen from above; each laser's vertical offset from the optical centre
(the manuals' "vertical correction", mm) is added to z, as the manuals say. Each firing's azimuth is its block's azimuth advanced by the
packet's rotation rate (first to last block azimuth over their time apart) times the firing's time
after the block's first firing: the manuals' "precise azimuth", with the rate of the whole packet
rather than of one block gap, whose 0.01 deg quantization jitters by 5-10 %. A packet that cannot be decoded (length, block flag, product,
azimuth out of range) raises PacketError with the reason, for the caller to count.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PACKET_BYTES = 1206
BLOCKS, SLOTS = 12, 32
BLOCK_FLAG = 0xEEFF           # bytes FF EE read as little-endian
STRONGEST, LAST, DUAL = 0x37, 0x38, 0x39
RETURN_MODES = {STRONGEST: "strongest", LAST: "last", DUAL: "dual"}
# per point: which return it is
RETURN_STRONGEST, RETURN_LAST = 1, 2

_BLOCK = np.dtype([("flag", "<u2"), ("azimuth", "<u2"), ("ret", [("distance", "<u2"), ("reflectivity", "u1")], (SLOTS,))])
_PACKET = np.dtype([("blocks", _BLOCK, (BLOCKS,)), ("stamp_us", "<u4"), ("mode", "u1"), ("product", "u1")])
assert _PACKET.itemsize == PACKET_BYTES


class PacketError(ValueError):
    """A packet that cannot be decoded: its reason is what diagnostics count."""


@dataclass(frozen=True)
class VelodyneModel:
    """One model's calibration and timing, from its user manual."""
    name: str
    product_id: int
    elevation_deg: tuple[float, ...]       # per laser id (the order of the slots in a firing)
    azimuth_offset_deg: tuple[float, ...]  # per laser id, added to the block azimuth
    vertical_offset_mm: tuple[float, ...]  # per laser id, beam origin above the optical centre
    distance_unit_m: float
    firing_period_us: float                # one firing sequence (all lasers once, plus recharge)
    laser_period_us: float                 # between two consecutive firings in a sequence
    lasers_per_firing: int                 # lasers fired at the same instant (HDL-32E, VLP-32C: 2)

    @property
    def lasers(self) -> int:
        return len(self.elevation_deg)

    @property
    def ring(self) -> np.ndarray:
        """Ring per laser id: 0 the lowest beam, upward (ROS's convention)."""
        order = np.argsort(np.asarray(self.elevation_deg), kind="stable")
        ring = np.empty(self.lasers, np.uint16)
        ring[order] = np.arange(self.lasers, dtype=np.uint16)
        return ring


VLP16_ELEVATION = (-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0, -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0)
PUCK_HIRES_ELEVATION = (-10.0, 0.67, -8.67, 2.0, -7.33, 3.33, -6.0, 4.67, -4.67, 6.0, -3.33, 7.33, -2.0, 8.67,
                        -0.67, 10.0)
HDL32_ELEVATION = (-30.67, -9.33, -29.33, -8.0, -28.0, -6.67, -26.67, -5.33, -25.33, -4.0, -24.0, -2.67, -22.67,
                   -1.33, -21.33, 0.0, -20.0, 1.33, -18.67, 2.67, -17.33, 4.0, -16.0, 5.33, -14.67, 6.67, -13.33,
                   8.0, -12.0, 9.33, -10.67, 10.67)
VLP32C_ELEVATION = (-25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148,
                    -5.333, 1.333, 0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0, 7.0,
                    4.667, -2.333, -2.0, 15.0, 10.333, -1.333)
VLP32C_AZIMUTH_OFFSET = (1.4, -4.2, 1.4, -1.4, 1.4, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4, -1.4, 4.2, -1.4, 4.2, -1.4, 1.4,
                         -4.2, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4, 1.4, -1.4, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4)
# vertical corrections (mm): VLP-16 and Puck Hi-Res from their manuals' tables; HDL-32E and VLP-32C
# as Velodyne's calibration files give them (LidarView's HDL-32 / VLP-32c, 2 and 4 decimals)
VLP16_VERTICAL_MM = (11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2)
PUCK_HIRES_VERTICAL_MM = (7.4, -0.9, 6.5, -1.8, 5.5, -2.7, 4.6, -3.7, 3.7, -4.6, 2.7, -5.5, 1.8, -6.5, 0.9, -7.4)
HDL32_VERTICAL_MM = (17.17, 4.76, 16.27, 4.07, 15.4, 3.38, 14.54, 2.7, 13.71, 2.02, 12.89, 1.35, 12.09, 0.67, 11.31,
                     0.0, 10.54, -0.67, 9.78, -1.35, 9.04, -2.02, 8.3, -2.7, 7.58, -3.38, 6.86, -4.07, 6.15, -4.76,
                     5.45, -5.45)
VLP32C_VERTICAL_MM = (19.7714, 0.7401, 1.234, 11.8694, 8.4801, 0.0, 0.4936, 6.5965, 5.397, -0.2464, 0.2464, 4.5672,
                      3.958, -0.9866, -0.4936, 2.9649, 3.4613, -1.234, -0.7401, 2.7174, 2.4693, -2.4693, -1.7274,
                      1.9751, 2.2221, -5.2061, -3.4613, 1.7274, 1.4806, -11.361, -7.7306, 0.9866)

MODELS = {m.name: m for m in (
    # name, product id, elevation, azimuth offset, vertical offset, distance unit, timing (manuals'
    # timing tables: VLP-16 16 x 2.304 us + recharge = 55.296 us; HDL-32E 32 x 1.152 + 9.216 = 46.080
    # us; VLP-32C 16 pairs x 2.304 us + recharge = 55.296 us)
    VelodyneModel("VLP-16", 0x22, VLP16_ELEVATION, (0.0,) * 16, VLP16_VERTICAL_MM, 0.002, 55.296, 2.304, 1),
    VelodyneModel("Puck-HiRes", 0x24, PUCK_HIRES_ELEVATION, (0.0,) * 16, PUCK_HIRES_VERTICAL_MM, 0.002, 55.296,
                  2.304, 1),
    VelodyneModel("HDL-32E", 0x21, HDL32_ELEVATION, (0.0,) * 32, HDL32_VERTICAL_MM, 0.002, 46.080, 1.152, 1),
    VelodyneModel("VLP-32C", 0x28, VLP32C_ELEVATION, VLP32C_AZIMUTH_OFFSET, VLP32C_VERTICAL_MM, 0.004, 55.296,
                  2.304, 2),
)}
BY_PRODUCT = {m.product_id: m for m in MODELS.values()}


@dataclass(frozen=True)
class VelodynePoints:
    """One packet's returns (distance 0 = no return, dropped)."""
    stamp_us: int                  # the packet's timestamp: us past the hour, first firing
    return_mode: str
    xyz_m: np.ndarray              # (N, 3) float64, sensor frame
    reflectivity: np.ndarray       # (N,) uint8
    ring: np.ndarray               # (N,) uint16
    time_offset_s: np.ndarray      # (N,) float64, after stamp_us
    azimuth_deg: np.ndarray        # (N,) float64, [0, 360): where the firing pointed
    return_kind: np.ndarray        # (N,) uint8: RETURN_STRONGEST / RETURN_LAST


@dataclass(frozen=True)
class _Table:
    """Per (block, slot) of one model and return mode (see VelodyneDecoder._table)."""
    t_us: np.ndarray                 # firing time after the packet stamp
    t_in_block_us: np.ndarray        # after its block's first firing
    azimuth_offset_deg: np.ndarray
    cos_el: np.ndarray
    sin_el: np.ndarray
    vertical_m: np.ndarray
    ring: np.ndarray
    time_s: np.ndarray


class VelodyneDecoder:
    """Packets of one sensor into points. `model` None: taken from each packet's product byte."""

    def __init__(self, model: str | None = None):
        if model is not None and model not in MODELS:
            raise ValueError(f"unknown Velodyne model {model!r}; known: {', '.join(MODELS)}")
        self.model = MODELS[model] if model else None
        self._tables: dict[tuple[str, bool], _Table] = {}

    def model_of(self, packet: bytes) -> VelodyneModel:
        if len(packet) != PACKET_BYTES:
            raise PacketError(f"{len(packet)} bytes, a data packet has {PACKET_BYTES}")
        if self.model is not None:
            return self.model
        m = BY_PRODUCT.get(packet[1205])
        if m is None:
            raise PacketError(f"unknown product id 0x{packet[1205]:02x}")
        return m

    def _table(self, m: VelodyneModel, dual: bool) -> "_Table":
        """Everything per (block, slot) that does not depend on the packet's contents, once per
        model and return mode: a packet's decode is then a few array operations on its own data."""
        key = (m.name, dual)
        if key not in self._tables:
            block = np.arange(BLOCKS)[:, None]
            slot = np.arange(SLOTS)[None, :]
            seq_per_block = SLOTS // m.lasers            # 2 firing sequences per block on a VLP-16
            laser = np.broadcast_to(slot % m.lasers, (BLOCKS, SLOTS)).astype(np.intp)
            seq_in_block = slot // m.lasers
            fired = (slot % m.lasers) // m.lasers_per_firing
            block_seq = (block // 2 if dual else block) * seq_per_block
            t_us = (m.firing_period_us * (block_seq + seq_in_block) + m.laser_period_us * fired).astype(np.float64)
            el = np.radians(np.asarray(m.elevation_deg))[laser]
            self._tables[key] = _Table(
                t_us=t_us, t_in_block_us=t_us - m.firing_period_us * block_seq,
                azimuth_offset_deg=np.asarray(m.azimuth_offset_deg)[laser], cos_el=np.cos(el), sin_el=np.sin(el),
                vertical_m=np.asarray(m.vertical_offset_mm)[laser] * 1e-3, ring=m.ring[laser], time_s=t_us * 1e-6)
        return self._tables[key]

    def decode(self, packet: bytes) -> VelodynePoints:
        """One packet's points; PacketError with the reason when it cannot be decoded."""
        out = self.decode_many([packet])[0]
        if isinstance(out, PacketError):
            raise out
        return out

    def decode_many(self, packets: list[bytes]) -> list[VelodynePoints | PacketError]:
        """Each packet's points, or the PacketError saying why it cannot be decoded, in order.
        Packets of one model and return mode are decoded together: numpy's cost per call, not per
        point, is what one 1206-byte packet costs, so a batch is several times cheaper."""
        out: list[VelodynePoints | PacketError | None] = [None] * len(packets)
        groups: dict[tuple[str, int], list[int]] = {}
        for i, pk in enumerate(packets):
            try:
                m = self.model_of(pk)
            except PacketError as e:
                out[i] = e
                continue
            groups.setdefault((m.name, pk[1204]), []).append(i)
        for (name, mode), idx in groups.items():
            for j, res in zip(idx, self._decode_group(MODELS[name], mode, [packets[i] for i in idx])):
                out[j] = res
        return out  # type: ignore[return-value]

    def _decode_group(self, m: VelodyneModel, mode: int, packets: list[bytes]) -> list[VelodynePoints | PacketError]:
        recs = np.frombuffer(b"".join(packets), _PACKET)
        blocks = recs["blocks"]                                   # (k, 12)
        flag_bad = blocks["flag"] != BLOCK_FLAG
        az = blocks["azimuth"].astype(np.float64)
        az_bad = az >= 36000
        dual = mode == DUAL
        tb = self._table(m, dual)
        rate = np.mod(az[:, -1] - az[:, 0], 36000.0) / (tb.t_us[-1, 0] - tb.t_us[0, 0])     # 0.01 deg / us
        azimuth = (az[:, :, None] + rate[:, None, None] * tb.t_in_block_us) * 0.01 + tb.azimuth_offset_deg
        distance = blocks["ret"]["distance"]                      # (k, 12, 32)
        valid = distance > 0
        if dual:     # even blocks: last return; odd: strongest (the second strongest if that is the last)
            kind = np.where((np.arange(BLOCKS) % 2 == 0)[:, None], RETURN_LAST, RETURN_STRONGEST) \
                * np.ones((BLOCKS, SLOTS), np.uint8)
            # a single echo is reported in both blocks: keep it once
            refl = blocks["ret"]["reflectivity"]
            valid[:, 1::2] &= ~((distance[:, 0::2] == distance[:, 1::2]) & (refl[:, 0::2] == refl[:, 1::2]))
        else:
            kind = np.full((BLOCKS, SLOTS), RETURN_LAST if mode == LAST else RETURN_STRONGEST, np.uint8)
        bad = flag_bad.any(axis=1) | az_bad.any(axis=1)
        valid &= ~bad[:, None, None]
        r = distance[valid] * m.distance_unit_m
        az_v = azimuth[valid]
        a = np.radians(az_v)
        sel = np.nonzero(valid)
        xy = r * tb.cos_el[sel[1], sel[2]]
        xyz = np.empty((r.size, 3))
        xyz[:, 0] = xy * np.cos(a)
        xyz[:, 1] = -xy * np.sin(a)
        xyz[:, 2] = r * tb.sin_el[sel[1], sel[2]] + tb.vertical_m[sel[1], sel[2]]
        ring, time_s = tb.ring[sel[1], sel[2]], tb.time_s[sel[1], sel[2]]
        reflectivity, kinds = blocks["ret"]["reflectivity"][valid], kind[sel[1], sel[2]]
        az_v = np.mod(az_v, 360.0)
        ends = np.cumsum(valid.reshape(len(packets), -1).sum(axis=1))
        name = RETURN_MODES.get(mode, f"0x{mode:02x}")
        out: list[VelodynePoints | PacketError] = []
        for j in range(len(packets)):
            if bad[j]:
                fb = np.flatnonzero(flag_bad[j])
                out.append(PacketError(f"block {fb[0]} flag 0x{int(blocks['flag'][j, fb[0]]):04x}, expected 0xeeff")
                           if fb.size else PacketError(f"azimuth {int(az[j].max())} out of 0..35999"))
                continue
            lo, hi = (ends[j - 1] if j else 0), ends[j]
            out.append(VelodynePoints(
                stamp_us=int(recs["stamp_us"][j]), return_mode=name, xyz_m=xyz[lo:hi], reflectivity=reflectivity[lo:hi],
                ring=ring[lo:hi], time_offset_s=time_s[lo:hi], azimuth_deg=az_v[lo:hi],
                return_kind=kinds[lo:hi].astype(np.uint8)))
        return out
