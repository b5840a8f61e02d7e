"""Visual front end: KLT tracking on the left image, stereo depth, RANSAC pose, keyframes.

Small pure functions over numpy arrays (each one a timed stage), and `FrontEnd`, which holds the
keyframe state between frames. Geometry is in the rectified left camera frame ("rect", OpenCV
optical axes); see calibration.py.

Per frame: track the keyframe's features from the previous left image into this one (pyramidal
Lucas-Kanade), rectify the tracked points, and solve the pose of this frame relative to the
keyframe by PnP + RANSAC against the keyframe's stereo-triangulated 3D points (stereo), or by an
essential matrix (mono: rotation and translation direction only). A new keyframe is taken when
inliers drop, the keyframe gets old or parallax grows; it keeps the surviving tracks, detects new
corners away from them, and triangulates all of them from its own stereo pair.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .calibration import CameraCalibration
from .dto import FeatureQuality


@dataclass
class FrontEndConfig:
    max_features: int = 250
    min_distance_px: int = 12
    corner_quality: float = 0.01
    klt_window_px: int = 15
    klt_levels: int = 3
    ransac_threshold_px: float = 1.5
    min_inliers: int = 12          # fewer: no visual fix this frame
    good_inliers: int = 40         # fewer: a weak fix (DEGRADED)
    keyframe_min_inliers: int = 70
    keyframe_max_age_s: float = 0.5
    keyframe_parallax_px: float = 40.0
    stereo_max_row_error_px: float = 1.5
    min_disparity_px: float = 0.5
    max_depth_m: float = 60.0
    pixel_sigma_px: float = 0.5    # floor of the measured reprojection noise
    covariance_inflation: float = 2.0   # sigma factor: 3D points are treated as exact in the Jacobian
    translation_sigma_fraction: float = 0.03    # + this fraction of |t| (stereo depth / scale error)
    essential_min_parallax_px: float = 1.0      # mono: below this median parallax, rotation only


@dataclass
class FrontEndResult:
    """`T_kf_cur`: this frame's rect-camera pose in the reference keyframe's rect camera (None when
    there is no visual fix); `cov6`: its covariance, GTSAM Pose3 tangent order (rotation, then
    translation), right perturbation. `new_keyframe`: this frame is now the reference."""

    status: str                      # "first" | "ok" | "weak" | "lost"
    keyframe_t_ns: int | None
    T_kf_cur: np.ndarray | None
    cov6: np.ndarray | None
    new_keyframe: bool
    quality: FeatureQuality
    keyframe_features: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)
    message: str = ""


class StageTimer:
    """Wall time per named stage of one frame (milliseconds), summed if a stage repeats."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (now - self._t) * 1e3
        self._t = now


# ---------------------------------------------------------------- stages


def to_gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return img if img.dtype == np.uint8 else cv2.convertScaleAbs(img)
    code = cv2.COLOR_RGBA2GRAY if img.shape[2] == 4 else cv2.COLOR_RGB2GRAY
    return cv2.cvtColor(img, code)


def detect_corners(gray: np.ndarray, max_corners: int, min_distance_px: int, quality: float,
                   avoid_px: np.ndarray | None = None) -> np.ndarray:
    """Shi-Tomasi corners (N, 2) float32, none within min_distance_px of `avoid_px`."""
    if max_corners <= 0:
        return np.zeros((0, 2), np.float32)
    mask = None
    if avoid_px is not None and len(avoid_px):
        mask = np.full(gray.shape[:2], 255, np.uint8)
        for x, y in np.asarray(avoid_px, np.int32):
            cv2.circle(mask, (int(x), int(y)), min_distance_px, 0, -1)
    c = cv2.goodFeaturesToTrack(gray, max_corners, quality, min_distance_px, mask=mask, blockSize=5)
    return np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)


def track_klt(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, window_px: int = 21,
              levels: int = 3, guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade: (new positions (N, 2), ok mask). Points leaving the image fail."""
    if len(pts) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.asarray(pts, np.float32).reshape(-1, 1, 2)
    flags = 0
    p1 = None
    if guess is not None:
        p1 = np.asarray(guess, np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st, _err = cv2.calcOpticalFlowPyrLK(
        prev, cur, p0, p1, winSize=(window_px, window_px), maxLevel=levels, flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03))
    p1 = p1.reshape(-1, 2)
    h, w = cur.shape[:2]
    ok = (st.ravel() == 1) & (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    return p1, ok


def stereo_points(left: np.ndarray, right: np.ndarray, pts_px: np.ndarray, calib: CameraCalibration,
                  cfg: FrontEndConfig) -> tuple[np.ndarray, np.ndarray]:
    """Match left features in the right image (KLT), rectify both, keep pairs on the same
    rectified row with positive disparity, triangulate: ((N, 3) points in rect frame, ok mask)."""
    n = len(pts_px)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    pr, ok = track_klt(left, right, pts_px, cfg.klt_window_px, cfg.klt_levels)
    rl = calib.rectify_left(pts_px)
    rr = calib.rectify_right(pr)
    disp = rl[:, 0] - rr[:, 0]
    ok &= np.abs(rl[:, 1] - rr[:, 1]) <= cfg.stereo_max_row_error_px
    ok &= disp >= cfg.min_disparity_px
    z = np.where(ok, calib.f * calib.baseline_m / np.maximum(disp, 1e-9), np.inf)
    ok &= z <= cfg.max_depth_m
    pts3 = np.column_stack([(rl[:, 0] - calib.cx) * z / calib.f, (rl[:, 1] - calib.cy) * z / calib.f, z])
    return pts3, ok


def pnp_covariance(points_cur: np.ndarray, f: float, sigma_px: float) -> np.ndarray:
    """6x6 covariance of a PnP pose from the reprojection Jacobian: sigma^2 (J^T J)^-1 for the
    left perturbation (rotation, translation) of T_cur_kf at points already in the current frame."""
    x, y, z = points_cur[:, 0], points_cur[:, 1], points_cur[:, 2]
    iz = 1.0 / z
    # d(u, v)/dX for u = f x/z, v = f y/z
    du = np.stack([f * iz, np.zeros_like(z), -f * x * iz * iz], axis=1)
    dv = np.stack([np.zeros_like(z), f * iz, -f * y * iz * iz], axis=1)
    # dX/d(rot) = -[X]x, dX/d(trans) = I
    def rows(d):
        rot = np.stack([-(d[:, 1] * z) + d[:, 2] * y, d[:, 0] * z - d[:, 2] * x,
                        -(d[:, 0] * y) + d[:, 1] * x], axis=1)
        return np.hstack([rot, d])
    J = np.vstack([rows(du), rows(dv)])
    info = J.T @ J
    return sigma_px ** 2 * np.linalg.inv(info + 1e-12 * np.eye(6))


def solve_pnp(points_kf: np.ndarray, rect_px: np.ndarray, calib: CameraCalibration,
              cfg: FrontEndConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Pose of the current rect camera from keyframe 3D points seen at `rect_px`:
    (T_cur_kf 4x4, inlier mask, cov6, rms px) or None."""
    if len(points_kf) < max(cfg.min_inliers, 6):
        return None
    K = np.array([[calib.f, 0, calib.cx], [0, calib.f, calib.cy], [0, 0, 1.0]])
    obj = np.ascontiguousarray(points_kf, np.float64)
    img = np.ascontiguousarray(rect_px, np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=100,
                                             reprojectionError=cfg.ransac_threshold_px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < cfg.min_inliers:
        return None
    mask = np.zeros(len(obj), bool)
    mask[inl.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    pc = obj @ R.T + tvec.ravel()
    proj = pc[:, :2] / pc[:, 2:3] * calib.f + [calib.cx, calib.cy]
    err = np.linalg.norm(proj - img, axis=1)
    mask = (err < cfg.ransac_threshold_px) & (pc[:, 2] > 0)
    n = int(mask.sum())
    if n < cfg.min_inliers:
        return None
    rms = float(np.sqrt(np.mean(err[mask] ** 2)))
    sigma = max(cfg.pixel_sigma_px, rms * np.sqrt(2 * n / max(2 * n - 6, 1))) * cfg.covariance_inflation
    cov = pnp_covariance(pc[mask], calib.f, sigma)
    # Stereo depth errors act as a scale error on the translation, which the reprojection
    # Jacobian (points taken as exact) does not see: add it in the keyframe axes.
    cov[3:, 3:] += (cfg.translation_sigma_fraction * np.linalg.norm(tvec)) ** 2 * np.eye(3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, tvec.ravel()
    return T, mask, cov, rms


def solve_essential(rect_kf: np.ndarray, rect_cur: np.ndarray, calib: CameraCalibration,
                    cfg: FrontEndConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Mono: rotation and translation *direction* of the current camera relative to the keyframe.
    The covariance gives the translation a 10 m sigma: the factor constrains rotation only and
    the IMU carries the scale."""
    if len(rect_kf) < max(cfg.min_inliers, 8):
        return None
    # Without parallax (a still or purely rotating camera) the essential matrix is undefined and
    # the five-point solver's polynomial degenerates (OpenCV 5 asserts in solvePoly); the rotation
    # alone is still well defined from the bearings.
    if np.median(np.linalg.norm(rect_cur - rect_kf, axis=1)) < cfg.essential_min_parallax_px:
        R, mask = solve_rotation(rect_kf, rect_cur, calib, cfg)
    else:
        try:
            E, inl = cv2.findEssentialMat(rect_kf, rect_cur, focal=calib.f, pp=(calib.cx, calib.cy),
                                          method=cv2.RANSAC, prob=0.999, threshold=cfg.ransac_threshold_px)
            if E is None or E.shape != (3, 3) or inl is None:
                return None
            _n, R, _t, _inl = cv2.recoverPose(E, rect_kf, rect_cur, focal=calib.f, pp=(calib.cx, calib.cy),
                                              mask=inl.copy())
        except cv2.error:
            R, inl = solve_rotation(rect_kf, rect_cur, calib, cfg)   # a degenerate configuration
        mask = np.asarray(inl).ravel() > 0
    if mask.sum() < cfg.min_inliers:
        return None
    # Rotation-only residual as the noise estimate (small-baseline between keyframes).
    sigma = cfg.pixel_sigma_px * cfg.covariance_inflation
    rot_var = (sigma / calib.f) ** 2 / mask.sum() * 4.0
    cov = np.diag([rot_var] * 3 + [100.0] * 3)
    T = np.eye(4)
    T[:3, :3] = R
    return T, mask, cov, sigma


def solve_rotation(rect_kf: np.ndarray, rect_cur: np.ndarray, calib: CameraCalibration,
                   cfg: FrontEndConfig) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (cur <- kf) that best maps the keyframe's bearings onto the current ones
    (Kabsch on unit rays), refined once on the bearings within the RANSAC threshold; the mask of
    those. Exact for a camera that did not translate."""
    def rays(px: np.ndarray) -> np.ndarray:
        b = np.column_stack([(px[:, 0] - calib.cx) / calib.f, (px[:, 1] - calib.cy) / calib.f, np.ones(len(px))])
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    a, b = rays(np.asarray(rect_kf, float)), rays(np.asarray(rect_cur, float))
    mask = np.ones(len(a), bool)
    for _ in range(2):
        U, _s, Vt = np.linalg.svd(a[mask].T @ b[mask])
        d = np.sign(np.linalg.det(Vt.T @ U.T))
        R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
        err_px = calib.f * np.linalg.norm(b - a @ R.T, axis=1)
        mask = err_px < cfg.ransac_threshold_px
        if mask.sum() < 3:
            break
    return R, mask


# ---------------------------------------------------------------- stateful front end


class FrontEnd:
    def __init__(self, calib: CameraCalibration, cfg: FrontEndConfig | None = None, stereo: bool = True):
        self.calib, self.cfg = calib, cfg or FrontEndConfig()
        self.stereo = stereo and calib.is_stereo
        self.keyframes = 0
        self.reset()

    def reset(self) -> None:
        self.kf_t_ns: int | None = None
        self.kf_points: np.ndarray = np.zeros((0, 3))   # stereo: 3D rect; mono: rect px (N, 2)
        self.kf_px: np.ndarray = np.zeros((0, 2), np.float32)  # where they were in the keyframe image
        self.cur_px: np.ndarray = np.zeros((0, 2), np.float32)
        self.prev_gray: np.ndarray | None = None

    def _make_keyframe(self, t_ns: int, gray: np.ndarray, right: np.ndarray | None,
                       keep_px: np.ndarray, timer: StageTimer) -> None:
        """`right`: the right image as it came (converted to gray here: only keyframes use it)."""
        cfg = self.cfg
        new = detect_corners(gray, cfg.max_features - len(keep_px), cfg.min_distance_px,
                             cfg.corner_quality, keep_px)
        timer.lap("detect")
        px = np.vstack([np.asarray(keep_px, np.float32).reshape(-1, 2), new])
        if self.stereo:
            gray_r = to_gray(right)
            timer.lap("gray")
            pts3, ok = stereo_points(gray, gray_r, px, self.calib, cfg)
            timer.lap("stereo")
            self.kf_points, px = pts3[ok], px[ok]
        else:
            self.kf_points = self.calib.rectify_left(px)
        self.kf_px, self.cur_px, self.kf_t_ns = px, px.copy(), t_ns
        self.keyframes += 1

    def process(self, t_ns: int, left: np.ndarray, right: np.ndarray | None = None) -> FrontEndResult:
        cfg, timer = self.cfg, StageTimer()
        gray = to_gray(left)
        timer.lap("gray")
        if self.stereo and right is None:
            raise ValueError("stereo front end needs a right image")
        right_img = right if self.stereo else None   # made gray only for a keyframe (_make_keyframe)
        if self.kf_t_ns is None or self.prev_gray is None:
            self._make_keyframe(t_ns, gray, right_img, np.zeros((0, 2)), timer)
            self.prev_gray = gray
            return FrontEndResult("first", None, None, None, True, FeatureQuality(tracked=len(self.cur_px)),
                                  len(self.kf_px), timer.ms, "new keyframe, no reference yet")
        ref_t = self.kf_t_ns
        cur, ok = track_klt(self.prev_gray, gray, self.cur_px, cfg.klt_window_px, cfg.klt_levels)
        timer.lap("track")
        n_before = len(self.cur_px)
        pts, kf_pts, kf_px, cur = self.kf_points[ok], self.kf_points[ok], self.kf_px[ok], cur[ok]
        tracked = len(cur)
        quality = FeatureQuality(tracked=tracked, lost=n_before - tracked)
        rect = self.calib.rectify_left(cur)
        timer.lap("rectify")
        sol = None
        if tracked >= cfg.min_inliers:
            sol = solve_pnp(pts, rect, self.calib, cfg) if self.stereo else solve_essential(kf_pts, rect, self.calib, cfg)
        timer.lap("pose")
        if sol is None:
            # No fix: start over from this image so tracking can re-acquire on the next frame.
            self._make_keyframe(t_ns, gray, right_img, np.zeros((0, 2)), timer)
            self.prev_gray = gray
            return FrontEndResult("lost", ref_t, None, None, True, quality, len(self.kf_px), timer.ms,
                                  f"no visual fix ({tracked} features tracked)")
        T_cur_kf, mask, cov, rms = sol
        quality.inliers = int(mask.sum())
        quality.mean_parallax_px = float(np.mean(np.linalg.norm(cur[mask] - kf_px[mask], axis=1)))
        quality.mean_reprojection_error_px = rms
        self.kf_points, self.kf_px, self.cur_px = kf_pts[mask], kf_px[mask], cur[mask]
        status = "ok" if quality.inliers >= cfg.good_inliers else "weak"
        new_kf = (quality.inliers < cfg.keyframe_min_inliers
                  or (t_ns - ref_t) * 1e-9 >= cfg.keyframe_max_age_s
                  or quality.mean_parallax_px >= cfg.keyframe_parallax_px)
        if new_kf:
            self._make_keyframe(t_ns, gray, right_img, self.cur_px, timer)
        self.prev_gray = gray
        return FrontEndResult(status, ref_t, np.linalg.inv(T_cur_kf), cov, new_kf, quality,
                              len(self.kf_px), timer.ms)
