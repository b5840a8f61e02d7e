"""sensor_msgs/PointCloud2 of any field layout -> our PointCloud, in numpy (no Zenoh, no ROS).

A vendor's ROS 2 driver packs its own point type: Velodyne (x, y, z, intensity, ring uint16, time
float32 s), Ouster (x, y, z, intensity, t uint32 ns, reflectivity, ring, ambient, range, padded to
48 bytes), Livox (x, y, z, intensity, tag, line, timestamp float64 ns). What we need of any of
them is float32 x, y, z; what we keep when present is intensity, the laser's row (ring, or Livox's
line) and when each point was measured (time_offset_s after the header stamp). Everything else is
skipped by offset, so padding and fields we do not know cost nothing.

It must never guess a unit it does not know: a time field of another name or type is not read,
and one that puts a point more than MAX_SWEEP_S from the stamp is refused as a unit mismatch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from aeroperception.schemas import Header, NDArray, PointCloud

# sensor_msgs/PointField datatypes
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FLOAT32 = 7
# Per-point time fields a driver's type may carry: (name, datatype) -> (what it is, scale to seconds).
#   relative: seconds after header.stamp once scaled; absolute: nanoseconds since the epoch.
TIME_FIELDS = {
    ("time", 7): ("relative", 1.0),        # Velodyne ROS driver: float32 s after the stamp
    ("t", 6): ("relative", 1e-9),          # Ouster ROS driver: uint32 ns after the stamp
    ("timestamp", 8): ("absolute", 1e-9),  # Livox ROS driver 2: float64 ns since the epoch
}
RING_FIELDS = ("ring", "line")             # the laser's row: Velodyne / Ouster ring, Livox line
MAX_SWEEP_S = 1.0                          # a point further than this from the stamp: wrong unit


class LayoutError(ValueError):
    """A PointCloud2 we cannot read: no float32 x/y/z, fields outside the point, short data."""


@dataclass(frozen=True)
class Layout:
    """Where our fields sit in one point of `point_step` bytes (a numpy structured dtype)."""

    dtype: np.dtype
    intensity: bool
    ring: str | None
    time: tuple[str, str, float] | None     # (field, "relative" | "absolute", scale to s / ns)

    @classmethod
    def of(cls, fields: list[Any], point_step: int, is_bigendian: bool) -> "Layout":
        """From the message's PointFields (objects with name, offset, datatype, count)."""
        by_name = {f.name: f for f in fields}
        order = ">" if is_bigendian else "<"
        missing = [n for n in "xyz" if n not in by_name or by_name[n].datatype != FLOAT32 or by_name[n].count != 1]
        if missing:
            have = ", ".join(f"{f.name}:{DATATYPES.get(f.datatype, f.datatype)}" for f in fields) or "none"
            raise LayoutError(f"PointCloud2 needs float32 x, y, z (wrong or missing: {', '.join(missing)}; fields: {have})")
        names, formats, offsets = [], [], []

        def take(name: str) -> None:
            f = by_name[name]
            code = DATATYPES.get(f.datatype)
            if code is None:
                raise LayoutError(f"PointCloud2 field {name!r} has unknown datatype {f.datatype}")
            size = np.dtype(code).itemsize
            if f.offset < 0 or f.offset + size > point_step:
                raise LayoutError(f"PointCloud2 field {name!r} (offset {f.offset}, {size} bytes) "
                                  f"lies outside the {point_step}-byte point")
            names.append(name)
            formats.append(order + code)
            offsets.append(f.offset)

        for n in "xyz":
            take(n)
        intensity = "intensity" in by_name and by_name["intensity"].count == 1
        if intensity:
            take("intensity")
        ring = next((n for n in RING_FIELDS if n in by_name and by_name[n].count == 1
                     and by_name[n].datatype in (2, 4)), None)
        if ring:
            take(ring)
        time = next(((n, *TIME_FIELDS[(n, by_name[n].datatype)]) for n, _ in TIME_FIELDS
                     if n in by_name and (n, by_name[n].datatype) in TIME_FIELDS and by_name[n].count == 1), None)
        if time:
            take(time[0])
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
        return cls(dtype, intensity, ring, time)


def decode(msg: Any, stamp_ns: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(points float32 (N, 3), {"intensity" | "ring" | "time_offset_s": per-point arrays}) of a
    PointCloud2 (fields, point_step, row_step, height, width, is_bigendian, data); points with a
    non-finite x, y or z dropped whatever is_dense claims. Raises LayoutError."""
    height, width, step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if step <= 0:
        raise LayoutError(f"PointCloud2 point_step {step}")
    layout = Layout.of(list(msg.fields), step, bool(msg.is_bigendian))
    if row_step < width * step:
        raise LayoutError(f"PointCloud2 row_step {row_step} < width {width} x point_step {step}")
    data = np.frombuffer(memoryview(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    need = (height - 1) * row_step + width * step if height else 0
    if data.size < need:
        raise LayoutError(f"PointCloud2 data has {data.size} bytes, {height} rows of {width} points need {need}")
    if height == 0 or width == 0:
        rows = np.zeros(0, layout.dtype)
    elif height == 1 or row_step == width * step:
        rows = data[:height * width * step].view(layout.dtype) if row_step == width * step else \
            data[:width * step].view(layout.dtype)
    else:   # padded rows: the first width * point_step bytes of each
        rows = np.lib.stride_tricks.as_strided(data, (height, width * step), (row_step, 1))
        rows = np.ascontiguousarray(rows).reshape(-1).view(layout.dtype)
    xyz = np.empty((rows.size, 3), np.float32)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = rows["x"], rows["y"], rows["z"]
    keep = np.isfinite(xyz).all(axis=1)
    everything = bool(keep.all())
    pts = xyz if everything else xyz[keep]
    sel = (lambda a: a) if everything else (lambda a: a[keep])
    extra: dict[str, np.ndarray] = {}
    if layout.intensity:
        extra["intensity"] = sel(rows["intensity"]).astype(np.float32)
    if layout.ring:
        extra["ring"] = sel(rows[layout.ring]).astype(np.uint16)
    if layout.time:
        name, kind, scale = layout.time
        t = sel(rows[name]).astype(np.float64)
        offset = t * scale if kind == "relative" else (t - stamp_ns) * scale
        if offset.size and np.nanmax(np.abs(offset)) > MAX_SWEEP_S:
            raise LayoutError(f"PointCloud2 field {name!r} puts points {np.nanmax(np.abs(offset)):.3g} s from the "
                              f"stamp (read as {'s' if scale == 1.0 else 'ns'}"
                              f"{' since the epoch' if kind == 'absolute' else ' after the stamp'}): not that unit")
        extra["time_offset_s"] = offset.astype(np.float32)
    return pts, extra


def point_cloud(msg: Any, header: Header) -> PointCloud:
    """Our PointCloud of a ROS PointCloud2 (`header` already converted from the ROS one)."""
    pts, extra = decode(msg, header.stamp_ns)
    return PointCloud(header=header, points=NDArray.from_numpy(pts),
                      **{k: NDArray.from_numpy(np.ascontiguousarray(v)) for k, v in extra.items()})
