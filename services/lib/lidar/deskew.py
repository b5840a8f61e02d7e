"""Motion compensation of a LiDAR sweep: a spinning sensor measures its points over the whole
rotation (100 ms at 10 Hz) while the vehicle moves, so a wall seen at the start and at the end of
the sweep is smeared by the distance flown and the angle turned meanwhile (1 m and 6 deg at 10 m/s
and 1 rad/s). Each point is moved from the sensor's pose when it was measured to the sensor's
pose at the scan's stamp (its first point), using the vehicle's poses around the sweep (state/vehicle,
interpolated: PoseHistory.at) and the declared extrinsics body <- sensor.

The sweep is cut into `bins` slices of equal time; the correction is computed at the slice edges
(one pose lookup each) and each point takes the blend of the two around its own time, so the cost
is a few dozen lookups and two batched rotations of the points whatever the point count.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aeroperception.services.lib.pose_history import PoseHistory


@dataclass(frozen=True)
class Mount:
    """Where the sensor sits: x_body = r_body_sensor @ x_sensor + t_body_sensor (FLU, metres)."""

    r_body_sensor: np.ndarray
    t_body_sensor: np.ndarray


def deskew(points: np.ndarray, time_offset_s: np.ndarray, stamp_ns: int, poses: PoseHistory, mount: Mount,
           tolerance_s: float = 0.05, bins: int = 32) -> tuple[np.ndarray | None, str]:
    """(points in the sensor frame at `stamp_ns`, "") or (None, why) when the poses do not cover the
    sweep (then the caller decides: use the scan as measured, or drop it). `points` (N, 3) in the
    sensor frame as measured, `time_offset_s` (N,) seconds after `stamp_ns`."""
    n = len(points)
    if n == 0:
        return points, ""
    t = np.asarray(time_offset_s, np.float64)
    if t.shape != (n,) or not np.all(np.isfinite(t)):
        return None, f"time_offset_s has {t.shape} entries, not one finite per point ({n})"
    t0, t1 = float(t.min()), float(t.max())
    if t0 < -1e-3 or t1 > 1.0:
        return None, f"time offsets {t0:.3f}..{t1:.3f} s are not one sweep after the stamp"
    ref = poses.at(stamp_ns, tolerance_s)
    if ref is None:
        return None, "no vehicle pose at the scan's stamp"
    if t1 <= 0.0:
        return points, ""
    edges = np.linspace(0.0, t1, bins + 1)
    r_ws_ref, p_ws_ref = _world_sensor(ref, mount)
    rot = np.empty((bins + 1, 3, 3))
    trans = np.empty((bins + 1, 3))
    for b, te in enumerate(edges):
        p = poses.at(stamp_ns + int(te * 1e9), tolerance_s)
        if p is None:
            return None, f"no vehicle pose {te * 1e3:.0f} ms into the sweep"
        r_ws, p_ws = _world_sensor(p, mount)
        # sensor(t) -> world -> sensor(stamp)
        rot[b] = r_ws_ref.T @ r_ws
        trans[b] = r_ws_ref.T @ (p_ws - p_ws_ref)
    # each point between the two slice edges around its time, blended linearly (the rotation across
    # one slice is a few mrad: the blend's error is its square)
    x = np.clip(t / t1, 0.0, 1.0) * bins
    k = np.minimum(x.astype(np.int64), bins - 1)
    f = (x - k)[:, None]
    pts = np.asarray(points, np.float64)
    out = np.empty_like(pts)
    order = np.argsort(k, kind="stable")
    cuts = np.searchsorted(k[order], np.arange(bins + 1))
    for b in range(bins):
        idx = order[cuts[b]:cuts[b + 1]]
        if idx.size:
            p_b = pts[idx]
            out[idx] = p_b @ rot[b].T + trans[b] + f[idx] * (p_b @ (rot[b + 1] - rot[b]).T + (trans[b + 1] - trans[b]))
    return out.astype(points.dtype, copy=False), ""


def _world_sensor(pose, mount: Mount) -> tuple[np.ndarray, np.ndarray]:
    r_wb = pose.r_world_body
    return r_wb @ mount.r_body_sensor, pose.position_m + r_wb @ mount.t_body_sensor
