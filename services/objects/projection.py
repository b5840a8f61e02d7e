"""Where a detection is in the world: a 2D box + the camera's pose at the image's stamp -> an ENU
point with a covariance.

Two ways to the range, both from the box alone (no per-pixel depth map is ever built):
- stereo: the median block-matched disparity in the box's inner region (a rectified pair:
  depth = fx * baseline / disparity);
- ground: the box centre's ray meets a horizontal plane at the object's mid-height above flat
  ground (the ground at the flight controller's home altitude, the object's height from its class).
Each position's covariance is the measurement's first-order propagation (pixel noise, disparity
noise, object height) plus the pose's own uncertainty, so it grows with range by construction.
Frames: camera optical (x right, y down, z forward), body FLU, world ENU.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from aeroperception.schemas import CameraInfo
from aeroperception.services.lib.pose_history import PoseSample
from aeroperception.services.runtime.rotations import quat_to_rotmat


@dataclass(frozen=True)
class Camera:
    """A pinhole camera on the body: intrinsics, and (for a stereo pair) the baseline."""

    fx: float
    fy: float
    cx: float
    cy: float
    r_body_cam: np.ndarray
    t_body_cam_m: np.ndarray
    baseline_m: float = 0.0

    @classmethod
    def from_infos(cls, left: CameraInfo, right: CameraInfo | None = None) -> "Camera":
        k = left.K.to_numpy()
        baseline = 0.0
        if right is not None:
            p = right.P.to_numpy()
            baseline = -p[0, 3] / p[0, 0] if p[0, 0] else 0.0
            if baseline <= 0.0:
                baseline = float(np.linalg.norm(right.T_body_camera.position.to_array()
                                                - left.T_body_camera.position.to_array()))
        return cls(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                   quat_to_rotmat(left.T_body_camera.orientation.to_array()),
                   left.T_body_camera.position.to_array(), float(baseline))

    def world_pose(self, pose: PoseSample) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_cam, camera origin in ENU) at this vehicle pose: once per frame."""
        r_wb = quat_to_rotmat(pose.q_enu_flu)
        return r_wb @ self.r_body_cam, pose.position_m + r_wb @ self.t_body_cam_m

    def rays(self, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
        """(k, 3) directions (optical frame, z = 1) through pixels in the continuous convention
        (the image spans [0, W]: pixel centres at i + 0.5, the pinhole's at i)."""
        return np.stack([(u_px - 0.5 - self.cx) / self.fx, (v_px - 0.5 - self.cy) / self.fy, np.ones_like(u_px)], 1)


@dataclass(frozen=True)
class Noise:
    """1-sigma noise of what a position is computed from (contract parameters)."""

    pixel_px: float = 2.0               # box centre
    disparity_px: float = 0.25          # median disparity in the box
    height_m: float = 0.3               # object's mid-height above the ground (class table)
    position_m: float = 0.1             # vehicle position
    attitude_rad: float = 0.01          # vehicle/camera attitude


@dataclass(frozen=True)
class Measurement:
    """One detection placed in the world."""

    position_m: np.ndarray              # ENU, the object's centre
    covariance_m2: np.ndarray           # 3x3 ENU
    range_m: float
    method: str                         # "stereo" or "ground"


def _measure(points, x: np.ndarray, sigmas: np.ndarray, origin: np.ndarray, noise: Noise,
             method: str) -> list[Measurement | None]:
    """points(x) for each row of x (k, n) as a Measurement: the covariance propagated from
    independent input noise `sigmas` (n,) by central differences (step = one sigma: linearised
    over the noise's own scale) plus the pose's (the vehicle's position, and its attitude times
    the range). `points` maps (m, n) inputs to (m, 3) points, NaN where undefined; a row undefined
    anywhere in its neighbourhood is None. All rows in one call: a frame's boxes cost one numpy
    pass, not one each."""
    k, n = x.shape
    steps = np.diag(sigmas)
    xs = np.concatenate([x[:, None, :], x[:, None, :] + steps, x[:, None, :] - steps], axis=1)
    pts = points(xs.reshape(-1, n)).reshape(k, 2 * n + 1, 3)
    ok = ~np.isnan(pts).any(axis=(1, 2))
    jac = (pts[:, 1:n + 1] - pts[:, n + 1:]) / 2.0
    p = pts[:, 0]
    r = np.linalg.norm(p - origin, axis=1)
    cov = np.einsum("kni,knj->kij", jac, jac) + np.eye(3) * (noise.position_m ** 2 + (r * noise.attitude_rad) ** 2)[:, None, None]
    return [Measurement(p[i], cov[i], float(r[i]), method) if ok[i] else None for i in range(k)]


def locate_on_ground(cam: Camera, view: tuple[np.ndarray, np.ndarray], u_px: float, v_px: float, centre_height_m: float,
                     noise: Noise, max_range_m: float, size_m: tuple[float, float, float] | None = None) -> Measurement | None:
    """The box centre's ray meets the horizontal plane z = centre_height_m (ENU). None when the ray
    does not descend to it within max_range_m (at or above the horizon). With the object's typical
    `size_m`, the ray is aimed at the object's centre instead (box_centre_offset_px)."""
    return locate_many_on_ground(cam, view, np.array([[u_px, v_px, centre_height_m]]), noise, max_range_m, [size_m])[0]


def locate_many_on_ground(cam: Camera, view: tuple[np.ndarray, np.ndarray], uvz: np.ndarray, noise: Noise,
                          max_range_m: float, sizes: list[tuple[float, float, float] | None] | None = None
                          ) -> list[Measurement | None]:
    """locate_on_ground for k boxes at once: rows (u px, v px, centre height m). With `sizes` (each
    row's, or None) each row is aimed at its object's centre first (centre_aims); without, the rows
    are aimed already."""
    r_wc, origin = view

    def points(x: np.ndarray) -> np.ndarray:
        d = cam.rays(x[:, 0], x[:, 1]) @ r_wc.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x[:, 2] - origin[2]) / d[:, 2]
            p = origin + d * t[:, None]
        bad = ~(t > 0) | (np.abs(d[:, 2]) < 1e-9) | (np.linalg.norm(p - origin, axis=1) > max_range_m)
        p[bad] = np.nan
        return p

    x = np.array(uvz, float)
    if sizes is not None:
        x[:, :2] -= centre_aims(cam, view, x, sizes)
    return _measure(points, x, np.array([noise.pixel_px, noise.pixel_px, noise.height_m]), origin, noise, "ground")


def centre_aims(cam: Camera, view: tuple[np.ndarray, np.ndarray], uvz: np.ndarray,
                sizes: list[tuple[float, float, float] | None]) -> np.ndarray:
    """(k, 2) px from each box's centre to where its object's centre projects (box_centre_offset_px
    at the point the box centre's ray meets the plane z = centre height; rows (u px, v px, centre
    height m)); 0 where the size is None or the ray does not descend."""
    r_wc, origin = view
    out = np.zeros((len(uvz), 2))
    for i, size_m in enumerate(sizes):
        if size_m is None:
            continue
        u_px, v_px, centre_height_m = uvz[i]
        d = r_wc @ np.array([(u_px - 0.5 - cam.cx) / cam.fx, (v_px - 0.5 - cam.cy) / cam.fy, 1.0])
        if d[2] < -1e-9:                        # the ray descends: where it meets the plane, unaimed
            off = box_centre_offset_px(cam, view, origin + d * ((centre_height_m - origin[2]) / d[2]), size_m)
            if off is not None:
                out[i] = off
    return out


def locate_by_disparity(cam: Camera, view: tuple[np.ndarray, np.ndarray], u_px: float, v_px: float, disparity_px: float,
                        noise: Noise) -> Measurement | None:
    """The box centre at depth fx * baseline / disparity along the optical axis."""
    return locate_many_by_disparity(cam, view, np.array([[u_px, v_px, disparity_px]]), noise)[0]


def locate_many_by_disparity(cam: Camera, view: tuple[np.ndarray, np.ndarray], uvd: np.ndarray,
                             noise: Noise) -> list[Measurement | None]:
    """locate_by_disparity for k boxes at once: rows (u px, v px, disparity px)."""
    r_wc, origin = view

    def points(x: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            depth = np.where(x[:, 2] > 0, cam.fx * cam.baseline_m / x[:, 2], np.nan)
        return origin + (cam.rays(x[:, 0], x[:, 1]) * depth[:, None]) @ r_wc.T

    return _measure(points, np.asarray(uvd, float), np.array([noise.pixel_px, noise.pixel_px, noise.disparity_px]),
                    origin, noise, "stereo")


def to_centre(m: Measurement, origin: np.ndarray, half_depth_m: float, sigma_m: float) -> Measurement:
    """Stereo measures the object's visible face; its centre lies about half its footprint farther
    along the (horizontal) line of sight. `sigma_m` (how much the footprint depends on the
    object's unknown heading) widens the covariance along that line."""
    d = m.position_m - origin
    d[2] = 0.0
    n = float(np.linalg.norm(d))
    if n < 1e-6:
        return m
    d /= n
    cov = m.covariance_m2 + sigma_m ** 2 * np.outer(d, d)
    return Measurement(m.position_m + d * half_depth_m, cov, m.range_m + half_depth_m, m.method)


@functools.lru_cache(maxsize=64)
def _headed_corners(size_m: tuple[float, float, float]) -> np.ndarray:
    """(4 * 8, 3) corners about the centre of a box of `size_m` at headings 0, 45, 90, 135 deg."""
    length, width, height = size_m
    corners = np.array([[dx, dy, dz] for dx in (-length / 2, length / 2) for dy in (-width / 2, width / 2)
                        for dz in (-height / 2, height / 2)])
    out = []
    for yaw in np.radians([0.0, 45.0, 90.0, 135.0]):
        c, s = np.cos(yaw), np.sin(yaw)
        out.append(corners @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]))
    return np.concatenate(out)


def box_centre_offset_px(cam: Camera, view: tuple[np.ndarray, np.ndarray], centre_m: np.ndarray,
                         size_m: tuple[float, float, float]) -> np.ndarray | None:
    """How far a box drawn around an object of typical size (length, width, height) at `centre_m`
    has its centre from where the object's centre projects (u, v px), over headings 0-135 degrees
    (unknown): seen from above, a long object's box takes in its near bottom and far top edges, so
    its centre is not its centre's projection (a car 17 m away end-on: ~ -0.5 m along the line of
    sight). None when a corner is behind the camera."""
    r_wc, origin = view
    pc = (np.vstack([_headed_corners(tuple(size_m)), np.zeros(3)]) + (centre_m - origin)) @ r_wc     # optical frame
    if (pc[:, 2] <= 0.1).any():
        return None
    uv = pc[:, :2] / pc[:, 2:] * (cam.fx, cam.fy)
    boxes = uv[:-1].reshape(4, 8, 2)
    return ((boxes.min(1) + boxes.max(1)) / 2).mean(0) - uv[-1]


def box_scale(cam: Camera, origin: np.ndarray, m: Measurement, box_height_px: float,
              size_m: tuple[float, float, float]) -> float:
    """The box's height over the height an object of typical size (length, width, height) at the
    placed point would fill: its side (height x cos) plus its top (mean footprint x sin of the
    angle it is seen down at). Near 1 (times the detector's margin) for a whole view from any range
    and height; much less for a partial one."""
    east, north, up = (float(c) for c in m.position_m - origin)
    down = math.atan2(-up, math.hypot(east, north))
    length, width, height = size_m
    typical_m = height * math.cos(down) + (length + width) / 2 * abs(math.sin(down))
    return box_height_px * m.range_m / cam.fy / typical_m


class GrayView:
    """An image seen as 8-bit gray where it is sliced (`view[y0:y1, x0:x1]`): a colour frame is
    converted strip by strip, only where boxes are. A plain 2-D uint8 array slices the same way."""

    def __init__(self, a: np.ndarray, to_gray: int | None = None):
        self.a, self.to_gray, self.shape = a, to_gray, a.shape[:2]

    def __getitem__(self, index) -> np.ndarray:
        part = self.a[index]
        if self.to_gray is not None:
            return cv2.cvtColor(np.ascontiguousarray(part), self.to_gray)
        return part if part.dtype == np.uint8 else (part >> 8).astype(np.uint8)


def box_disparity(left: np.ndarray | GrayView, right: np.ndarray | GrayView, box_xyxy: tuple[float, float, float, float],
                  max_disparity_px: int, inner_fraction: float = 0.5, min_valid: int = 8) -> float | None:
    """Median block-matched disparity (px, 1/16 resolution) over the inner `inner_fraction` of the
    box, from a rectified pair (grayscale arrays or GrayViews); None with fewer than `min_valid`
    matched pixels.

    Only a strip around the box is matched (the box plus the search range to its left), so the cost
    follows the box's size, not the image's."""
    h, w = left.shape[:2]
    block = 7
    ndisp = max(16, (max_disparity_px + 15) // 16 * 16)
    x0, y0, x1, y1 = box_xyxy
    mx, my = (x1 - x0) * (1 - inner_fraction) / 2, (y1 - y0) * (1 - inner_fraction) / 2
    ix0, ix1 = int(np.floor(x0 + mx)), int(np.ceil(x1 - mx))
    iy0, iy1 = int(np.floor(y0 + my)), int(np.ceil(y1 - my))
    ix0, iy0, ix1, iy1 = max(ix0, 0), max(iy0, 0), min(ix1, w), min(iy1, h)
    if ix1 - ix0 < 2 or iy1 - iy0 < 2:
        return None
    pad = block // 2 + 1
    sx0, sx1 = max(ix0 - ndisp - pad, 0), min(ix1 + pad, w)
    sy0, sy1 = max(iy0 - pad, 0), min(iy1 + pad, h)
    if sx1 - sx0 < ndisp + block:
        return None
    bm = cv2.StereoBM_create(numDisparities=ndisp, blockSize=block)
    bm.setTextureThreshold(5)
    bm.setUniquenessRatio(10)
    disp = bm.compute(np.ascontiguousarray(left[sy0:sy1, sx0:sx1]), np.ascontiguousarray(right[sy0:sy1, sx0:sx1]))
    inner = disp[iy0 - sy0:iy1 - sy0, ix0 - sx0:ix1 - sx0]
    valid = inner[inner > 0]
    if valid.size < min_valid:
        return None
    return float(np.median(valid)) / 16.0


def fuse(a: Measurement | None, b: Measurement | None, origin: np.ndarray, gate: float = 3.0) -> Measurement | None:
    """Both measurements combined by their information when they agree (squared Mahalanobis
    distance of the difference under gate**2 per axis); else the tighter one (smaller trace). The
    range is the fused point's from the camera at `origin` (a far stereo range, metres uncertain,
    agrees with a ground one it says little about: the point is the ground's, so is the range)."""
    if a is None or b is None:
        return a or b
    diff = a.position_m - b.position_m
    x = np.linalg.solve(a.covariance_m2 + b.covariance_m2, np.column_stack([diff, a.covariance_m2]))
    if float(diff @ x[:, 0]) > 3 * gate ** 2:
        return a if np.trace(a.covariance_m2) <= np.trace(b.covariance_m2) else b
    k = x[:, 1:].T                                      # Pa (Pa + Pb)^-1: the information-weighted mean
    cov = a.covariance_m2 - k @ a.covariance_m2
    p = a.position_m - k @ diff
    return Measurement(p, (cov + cov.T) / 2, float(np.linalg.norm(p - origin)), f"{a.method}+{b.method}")
