"""Pinhole cameras rendered by ray casting the scenario scene.

Conventions: images are row-major (v down, u right); pixel (u, v) has its centre at integer
coordinates, so K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with cx = (W - 1) / 2 projects a camera
point X to u = fx X/Z + cx exactly where the ray of pixel u was cast (the OpenCV / ROS CameraInfo
convention). Camera frames are optical (x right, y down, z forward); extrinsics are given as
R_body_camera / t_body_camera_m (camera -> FLU body). No distortion.

Speed (a 2-core machine has to run a 20 Hz stereo pair next to the LiDAR): rays are cast for a
half-resolution grid of 2x2 block centres; pixels whose four surrounding samples hit the same
plane are filled by bilinear upsampling of (1/z, u_tex/z, v_tex/z) -- quantities that are affine
in the pixel coordinates on a plane, so the upsampling is exact, not an approximation -- and only
pixels on silhouettes / plane edges are cast at full resolution. Texturing is one mipmapped
gather per pixel. `exact=True` casts every pixel (used by tests to check the fast path).
Surfaces thinner than ~2 px can be missed by the coarse grid.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..world.scenario import CameraConfig, DownCameraConfig
from ..world.scene import TEXTURE_LEVELS, TEXTURE_LOG2, TEXTURE_SIZE, Scene
from .frames import R_FLU_OPTICAL_FORWARD, pose_of, rot_y

LOD_BIAS = -0.5   # < 0: pick a slightly sharper mip level (more corners, a little aliasing)


@dataclass(frozen=True)
class CameraInfo:
    """Calibration as published next to the images (sensor_msgs/CameraInfo-like)."""
    frame_id: str
    width: int
    height: int
    k: tuple[float, ...]               # 3x3 row-major intrinsics
    d: tuple[float, ...]               # plumb_bob distortion, all zero
    p: tuple[float, ...]               # 3x4 row-major projection; p[3] = -fx * baseline for the right camera
    r_body_camera: tuple[float, ...]   # 3x3 row-major, optical -> FLU body
    t_body_camera_m: tuple[float, ...]  # optical origin in FLU body
    rate_hz: float
    encoding: str                      # "rgb8" or "mono8"
    distortion_model: str = "plumb_bob"


@dataclass
class CameraRender:
    """Image plus the per-pixel truth layers that fall out of rendering for free."""
    image: np.ndarray               # (H, W, 3) uint8 RGB or (H, W) uint8 mono
    depth_m: np.ndarray | None      # (H, W) float32 optical-axis depth z, inf where nothing was hit
    entity: np.ndarray | None       # (H, W) int32 scene entity id (Scene.entities), -1 for sky


class Camera:
    """One pinhole camera rigidly mounted on the body."""

    def __init__(self, scene: Scene, *, width: int, height: int, hfov_deg: float,
                 r_body_camera: np.ndarray, t_body_camera_m, frame_id: str,
                 rate_hz: float = 20.0, encoding: str = "rgb8", baseline_tx_m: float = 0.0):
        self.scene = scene
        self.width, self.height = width, height
        self.frame_id, self.rate_hz, self.encoding = frame_id, rate_hz, encoding
        self.fx = self.fy = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        self.cx, self.cy = (width - 1) / 2.0, (height - 1) / 2.0
        self.k = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        self.r_body_camera = np.asarray(r_body_camera, dtype=float)
        self.t_body_camera_m = np.asarray(t_body_camera_m, dtype=float)
        self._baseline_tx_m = baseline_tx_m

        u = (np.arange(width) - self.cx) / self.fx
        v = (np.arange(height) - self.cy) / self.fy
        xn, yn = np.meshgrid(u, v)
        # Optical ray directions (x, y, 1) per pixel, as 1-D columns; cast with these
        # unnormalised directions, t_hit is the depth z.
        self._x, self._y = xn.ravel().astype(np.float32), yn.ravel().astype(np.float32)
        self._coarse = width % 2 == 0 and height % 2 == 0 and width >= 8 and height >= 8
        if self._coarse:
            hc, wc = height // 2, width // 2
            uc = (2 * np.arange(wc) + 0.5 - self.cx) / self.fx   # 2x2 block centres
            vc = (2 * np.arange(hc) + 0.5 - self.cy) / self.fy
            xc, yc = np.meshgrid(uc, vc)
            self._coarse_x, self._coarse_y = xc.ravel().astype(np.float32), yc.ravel().astype(np.float32)
        self._level_off = scene.tex_level_offset.astype(np.int32)

    # ---- calibration ----

    def info(self) -> CameraInfo:
        p = np.hstack([self.k, [[-self.fx * self._baseline_tx_m], [0.0], [0.0]]])
        return CameraInfo(self.frame_id, self.width, self.height, tuple(self.k.ravel()), (0.0,) * 5,
                          tuple(p.ravel()), tuple(self.r_body_camera.ravel()),
                          tuple(self.t_body_camera_m), self.rate_hz, self.encoding)

    def world_pose(self, truth_or_pose) -> tuple[np.ndarray, np.ndarray]:
        """(R_enu_camera, camera origin ENU m) for a VehicleTruth or (position, q_enu_flu)."""
        pos, r_wb = pose_of(truth_or_pose)
        return r_wb @ self.r_body_camera, pos + r_wb @ self.t_body_camera_m

    def project(self, truth_or_pose, points_enu_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole projection of world points: ((N, 2) pixel coords, (N,) depth z m)."""
        r_wc, o = self.world_pose(truth_or_pose)
        pc = (np.atleast_2d(points_enu_m) - o) @ r_wc
        uv = pc[:, :2] / pc[:, 2:3] * [self.fx, self.fy] + [self.cx, self.cy]
        return uv, pc[:, 2]

    # ---- rendering ----

    def render(self, truth_or_pose, exact: bool = False) -> np.ndarray:
        """Image at the pose of `truth_or_pose` (the pose at the image stamp)."""
        return self._render(truth_or_pose, exact, layers=False).image

    def render_layers(self, truth_or_pose, exact: bool = False) -> CameraRender:
        """Image plus depth and entity-id images (for tests, eval and debugging views)."""
        return self._render(truth_or_pose, exact, layers=True)

    def _frame_tables(self, r_wc: np.ndarray, o: np.ndarray) -> dict[str, np.ndarray]:
        """Per-plane constants for this pose, in camera coordinates and texel units, as 1-D
        float32 columns (np.take on 1-D tables is several times faster than row gathers)."""
        sc = self.scene
        inv = sc.plane_inv_texel
        n_c = sc.plane_normal @ r_wc
        e1 = (sc.plane_e1 @ r_wc) * inv[:, None]
        e2 = (sc.plane_e2 @ r_wc) * inv[:, None]
        # Texture coordinate of the camera origin, wrapped to one tile (mips wrap consistently)
        # so float32 keeps sub-texel precision anywhere in the world.
        s0 = np.mod((sc.plane_e1 @ o + sc.plane_tex_offset_m[:, 0]) * inv, TEXTURE_SIZE)
        t0 = np.mod((sc.plane_e2 @ o + sc.plane_tex_offset_m[:, 1]) * inv, TEXTURE_SIZE)
        cols = {"s0": s0, "t0": t0, "lod": inv / self.fx}
        for k in range(3):
            cols[f"n{k}"], cols[f"e1{k}"], cols[f"e2{k}"] = n_c[:, k], e1[:, k], e2[:, k]
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in cols.items()}

    @staticmethod
    def _surface(tab: dict[str, np.ndarray], plane: np.ndarray, z: np.ndarray, x: np.ndarray,
                 y: np.ndarray):
        """Per-sample (1/z, s/z, t/z, mip level) from the hit plane, depth and ray (x, y, 1)."""
        g = lambda key: np.take(tab[key], plane)
        w = 1.0 / z
        a = g("s0") * w + g("e10") * x + g("e11") * y + g("e12")
        b = g("t0") * w + g("e20") * x + g("e21") * y + g("e22")
        # Footprint of a pixel on the surface in texels: z/fx/cos(incidence)/texel.
        nd = np.abs(g("n0") * x + g("n1") * y + g("n2"))
        cos = nd / np.sqrt(x * x + y * y + 1.0)
        fp = z * g("lod") / np.maximum(cos, 1e-6)
        level = np.clip(np.rint(np.log2(np.maximum(fp, 1e-6)) + LOD_BIAS), 0, TEXTURE_LEVELS - 1)
        return w, a, b, level.astype(np.int32)

    def _render(self, truth_or_pose, exact: bool, layers: bool) -> CameraRender:
        sc = self.scene
        r_wc, o = self.world_pose(truth_or_pose)
        tables = self._frame_tables(r_wc, o)
        h, w_ = self.height, self.width

        if exact or not self._coarse:
            z, plane = sc.cast_rays(sc.make_rays(o, r_wc, self._x, self._y))
            w, a, b, level = self._surface(tables, plane, z, self._x, self._y)
        else:
            hc, wc = h // 2, w_ // 2
            zc, pc = sc.cast_rays(sc.make_rays(o, r_wc, self._coarse_x, self._coarse_y))
            wcs, acs, bcs, lcs = self._surface(tables, pc, zc, self._coarse_x, self._coarse_y)
            # Full-res pixel (2i+a, 2j+b) is bilinearly interpolated from coarse samples
            # (i-1+a .. i+a, j-1+b .. j+b); where those four hit one plane the result is exact.
            # Elsewhere (silhouettes, plane edges, image border) the pixel is cast itself.
            grid = np.pad(pc.reshape(hc, wc), 1, constant_values=-1)
            one_plane = ((grid[:-1, :-1] == grid[1:, :-1]) & (grid[:-1, :-1] == grid[:-1, 1:])
                         & (grid[:-1, :-1] == grid[1:, 1:]))          # (hc + 1, wc + 1)
            exact_px = np.empty((h, w_), bool)
            for da in (0, 1):
                for db in (0, 1):
                    exact_px[da::2, db::2] = one_plane[da:da + hc, db:db + wc]
            size = (w_, h)
            up = lambda img: cv2.resize(img.reshape(hc, wc), size, interpolation=cv2.INTER_LINEAR).ravel()
            rep = lambda img: cv2.resize(img.reshape(hc, wc), size, interpolation=cv2.INTER_NEAREST).ravel()
            w, a, b = up(wcs), up(acs), up(bcs)
            plane, level = rep(pc), rep(lcs)
            edge_px = np.flatnonzero(~exact_px).astype(np.int32)
            if len(edge_px):
                x_e, y_e = self._x[edge_px], self._y[edge_px]
                z_e, p_e = sc.cast_rays(sc.make_rays(o, r_wc, x_e, y_e))
                w_e, a_e, b_e, l_e = self._surface(tables, p_e, z_e, x_e, y_e)
                w[edge_px], a[edge_px], b[edge_px] = w_e, a_e, b_e
                plane[edge_px], level[edge_px] = p_e, l_e

        # Mipmapped texture lookup: texel (s, t) at level L is (floor(s) >> L, floor(t) >> L).
        z = 1.0 / w
        si = np.floor(a * z).astype(np.int32)
        ti = np.floor(b * z).astype(np.int32)
        si >>= level
        ti >>= level
        mask = np.right_shift(np.int32(TEXTURE_SIZE - 1), level)
        si &= mask
        ti &= mask
        ti <<= TEXTURE_LOG2 - level
        idx = np.take(sc.plane_tex, plane)
        idx += np.take(self._level_off, level)
        idx += ti
        idx += si
        tex = np.take(sc.texels, idx).astype(np.uint16)
        shade = lambda lut: ((np.take(lut, plane) * tex + 128) >> 8).astype(np.uint8).reshape(h, w_)
        if self.encoding == "mono8":
            image = shade(sc.plane_gray)
        else:
            image = cv2.merge([shade(sc.plane_rgb_cols[c]) for c in range(3)])
        if not layers:
            return CameraRender(image, None, None)
        depth = np.where(plane < sc.num_planes, z, np.inf).astype(np.float32).reshape(h, w_)
        return CameraRender(image, depth, np.take(sc.plane_entity, plane).reshape(h, w_))


def camera_mount(pitch_down_deg: float) -> np.ndarray:
    """R_body_camera for a camera looking along body +x tilted down by pitch_down_deg
    (a positive rotation about FLU +y points the optical axis below the horizon)."""
    return rot_y(math.radians(pitch_down_deg)) @ R_FLU_OPTICAL_FORWARD


class StereoCamera:
    """Forward stereo pair (or a single camera when config.stereo is false).

    The left camera is the reference; the right one sits baseline_m along the left camera's
    optical +x, so both share orientation (a rectified pair: disparity = fx * baseline / z).
    """

    def __init__(self, scene: Scene, config: CameraConfig):
        self.config = config
        r_bc = camera_mount(config.pitch_down_deg)
        centre = np.asarray(config.position_body_m, dtype=float)
        half = r_bc[:, 0] * (config.baseline_m / 2.0 if config.stereo else 0.0)
        common = dict(width=config.width, height=config.height, hfov_deg=config.hfov_deg,
                      r_body_camera=r_bc, rate_hz=config.rate_hz, encoding=config.encoding)
        self.left = Camera(scene, t_body_camera_m=centre - half, frame_id="camera_left_optical", **common)
        self.right = (Camera(scene, t_body_camera_m=centre + half, frame_id="camera_right_optical",
                             baseline_tx_m=config.baseline_m, **common) if config.stereo else None)

    def render(self, truth_or_pose, exact: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """(left, right) images at one pose; right is None for a mono rig."""
        left = self.left.render(truth_or_pose, exact)
        return left, (self.right.render(truth_or_pose, exact) if self.right else None)

    def infos(self) -> list[CameraInfo]:
        return [c.info() for c in (self.left, self.right) if c is not None]


def make_down_camera(scene: Scene, config: DownCameraConfig) -> Camera:
    """Downward camera (optical axis = body -z, image top = body forward)."""
    return Camera(scene, width=config.width, height=config.height, hfov_deg=config.hfov_deg,
                  r_body_camera=camera_mount(90.0), t_body_camera_m=config.position_body_m,
                  frame_id="camera_down_optical", rate_hz=config.rate_hz, encoding=config.encoding)
