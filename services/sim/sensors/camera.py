"""Pinhole cameras rendered from the scenario scene (rasterised; ray cast as the reference).

Conventions: images are row-major (v down, u right); pixel (u, v) has its centre at integer
coordinates, so K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with cx = (W - 1) / 2 projects a camera
point X to u = fx X/Z + cx exactly where the ray of pixel u was cast (the OpenCV / ROS CameraInfo
convention). Camera frames are optical (x right, y down, z forward); extrinsics are given as
R_body_camera / t_body_camera_m (camera -> FLU body). No distortion.

Speed (a 2-core machine has to run a 20 Hz stereo pair next to the LiDAR): the scene's triangles
are rasterised with a z-buffer (camera_kernels.py, numba): coverage and depth are evaluated
exactly at each pixel centre, so every pixel sees the surface its ray would hit, including thin
poles and triangles partly behind the camera. One fused pass then textures and shades each pixel
(one mipmapped texel gather). `exact=True` casts a ray per pixel with Open3D instead (the
reference the tests and `aero bench sim` compare against) and shades it the same way.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..world.scenario import CameraConfig, DownCameraConfig
from ..world.scene import TEXTURE_LEVELS, TEXTURE_LOG2, Scene
from .frames import R_FLU_OPTICAL_FORWARD, pose_of, rot_y

LOD_BIAS = -0.5   # < 0: pick a slightly sharper mip level (more corners, a little aliasing)
# Mip level L is chosen where rint(log2(footprint texels) + LOD_BIAS) = L: from this footprint up.
_LEVEL_MIN_FOOTPRINT = 2.0 ** (np.arange(TEXTURE_LEVELS) - 0.5 - LOD_BIAS)


@dataclass(frozen=True)
class PinholeModel:
    """A rendered camera's pinhole model (no distortion), which sim/main.py publishes as the CameraInfo
    message next to its images."""
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
        # Optical ray directions (x, y, 1) per pixel for the reference ray cast, as 1-D columns;
        # cast with these unnormalised directions, t_hit is the depth z.
        self._x, self._y = xn.ravel().astype(np.float32), yn.ravel().astype(np.float32)
        # The rasteriser sees exactly the float32 geometry the ray caster holds.
        self._vertices = scene.vertices.astype(np.float64)
        self._triangles = scene.triangles.astype(np.int32)
        self._level_off = scene.tex_level_offset.astype(np.int64)
        # The z-buffer's plane ids (and the sky's, num_planes) as int16 when they fit: less memory
        # traffic between rasterize and shade, ~5 % of a frame, the same image.
        self._plane_dtype = np.int16 if scene.num_planes < np.iinfo(np.int16).max else np.int32
        self._colours = np.ascontiguousarray(scene.plane_gray[:, None] if encoding == "mono8" else scene.plane_rgb)

    # ---- calibration ----

    def info(self) -> PinholeModel:
        p = np.hstack([self.k, [[-self.fx * self._baseline_tx_m], [0.0], [0.0]]])
        return PinholeModel(self.frame_id, self.width, self.height, tuple(self.k.ravel()), (0.0,) * 5,
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

    def _render(self, truth_or_pose, exact: bool, layers: bool) -> CameraRender:
        from . import camera_kernels as kernels   # numba: only a process that renders pays its import
        sc = self.scene
        r_wc, o = self.world_pose(truth_or_pose)
        h, w = self.height, self.width
        if exact:
            z, plane = sc.cast_rays(sc.make_rays(o, r_wc, self._x, self._y))
            plane = plane.reshape(h, w)
            inv_z = (1.0 / z.astype(np.float64)).reshape(h, w)
        else:
            inv_z, plane = np.empty((h, w)), np.empty((h, w), self._plane_dtype)
            kernels.rasterize((self._vertices - o) @ r_wc, self._triangles, sc.tri_plane, self.fx, self.fy,
                              self.cx, self.cy, inv_z, plane, sc.num_planes)
        image = np.empty((h, w, self._colours.shape[1]), np.uint8)
        depth = np.empty((h, w) if layers else (0, 0), np.float32)
        entity = np.empty((h, w) if layers else (0, 0), np.int32)
        tab = kernels.plane_table(sc, r_wc, o, self.fx)
        kernels.shade(inv_z, plane, self.fx, self.fy, self.cx, self.cy, tab, sc.plane_tex, self._level_off,
                      _LEVEL_MIN_FOOTPRINT, sc.texels, TEXTURE_LOG2, self._colours, image, depth, entity,
                      sc.plane_entity)
        if self.encoding == "mono8":
            image = image.reshape(h, w)
        return CameraRender(image, depth, entity) if layers else CameraRender(image, None, None)


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

    def infos(self) -> list[PinholeModel]:
        return [c.info() for c in (self.left, self.right) if c is not None]


def make_down_camera(scene: Scene, config: DownCameraConfig) -> Camera:
    """Downward camera (optical axis = body -z, image top = body forward)."""
    return Camera(scene, width=config.width, height=config.height, hfov_deg=config.hfov_deg,
                  r_body_camera=camera_mount(90.0), t_body_camera_m=config.position_body_m,
                  frame_id="camera_down_optical", rate_hz=config.rate_hz, encoding=config.encoding)
