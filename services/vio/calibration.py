"""Camera calibration for the VIO: intrinsics, distortion and extrinsics of the left (and right)
camera from CameraInfo messages, and the stereo rectification computed from them.

All front-end geometry happens in the *rectified left* camera frame: feature points are
undistorted and rectified point-wise (cv2.undistortPoints with R1/P1) instead of remapping whole
images, which costs ~1 ms per 640x480 image pair and would touch 300k pixels to use 200.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aeroperception.schemas import CameraInfo
from aeroperception.services.runtime.rotations import quat_to_rotmat

SUPPORTED_DISTORTION = ("plumb_bob", "radtan", "radial-tangential", "none", "")


class CalibrationError(ValueError):
    """Calibration missing, inconsistent or of an unsupported model."""


def pose_matrix(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(pose.orientation.to_array())
    T[:3, 3] = pose.position.to_array()
    return T


@dataclass
class CameraCalibration:
    """Stereo (or mono) rig. `T_body_rect` is the rectified left camera's pose in the body frame;
    `f`, `cx`, `cy` its pinhole intrinsics; `baseline_m` 0 for mono."""

    width: int
    height: int
    K_left: np.ndarray
    D_left: np.ndarray
    T_body_left: np.ndarray
    K_right: np.ndarray | None = None
    D_right: np.ndarray | None = None
    T_body_right: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size {self.width}x{self.height} is not valid")
        for name in ("K_left", "K_right"):
            K = getattr(self, name)
            if K is not None and (not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0):
                raise CalibrationError(f"{name}: focal lengths must be positive and finite")
        size = (self.width, self.height)
        if self.is_stereo:
            T_r_l = np.linalg.inv(self.T_body_right) @ self.T_body_left   # left -> right camera
            R1, R2, P1, P2, *_ = cv2.stereoRectify(self.K_left, self.D_left, self.K_right, self.D_right,
                                                   size, T_r_l[:3, :3].copy(), T_r_l[:3, 3].reshape(3, 1).copy(),
                                                   flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
            self.baseline_m = float(-P2[0, 3] / P2[0, 0])
            if not self.baseline_m > 1e-3:
                raise CalibrationError(f"right camera is not to the right of the left one (baseline {self.baseline_m:.4f} m)")
        else:
            R1, R2, P1, P2 = np.eye(3), None, np.hstack([self.K_left, np.zeros((3, 1))]), None
            self.baseline_m = 0.0
        self.R1, self.R2, self.P1, self.P2 = R1, R2, P1, P2
        self.f = float(P1[0, 0])
        self.cx, self.cy = float(P1[0, 2]), float(P1[1, 2])
        T_left_rect = np.eye(4)
        T_left_rect[:3, :3] = R1.T
        self.T_body_rect = self.T_body_left @ T_left_rect

    @property
    def is_stereo(self) -> bool:
        return self.K_right is not None

    def rectify_left(self, pts_px: np.ndarray) -> np.ndarray:
        """Raw left-image pixels (N, 2) -> rectified pixels (N, 2)."""
        return _rectify(pts_px, self.K_left, self.D_left, self.R1, self.P1)

    def rectify_right(self, pts_px: np.ndarray) -> np.ndarray:
        return _rectify(pts_px, self.K_right, self.D_right, self.R2, self.P2)

    def check_image(self, img: np.ndarray | None, side: str) -> str | None:
        """None if `img` fits this calibration, else why not (one line)."""
        if img is None:
            return f"no {side} image"
        if img.ndim not in (2, 3) or img.shape[0] != self.height or img.shape[1] != self.width:
            return (f"{side} image is {'x'.join(map(str, img.shape[1::-1]))} but the calibration "
                    f"is {self.width}x{self.height}")
        return None

    @classmethod
    def from_camera_infos(cls, left: CameraInfo, right: CameraInfo | None = None) -> "CameraCalibration":
        for info in (left, right):
            if info is not None and info.distortion_model not in SUPPORTED_DISTORTION:
                raise CalibrationError(f"{info.header.frame_id or 'camera'}: distortion model "
                                       f"{info.distortion_model!r} not supported (plumb_bob / radtan)")
        if right is not None and (right.width, right.height) != (left.width, left.height):
            raise CalibrationError(f"left is {left.width}x{left.height} but right is {right.width}x{right.height}")
        K = lambda i: np.asarray(i.K.to_numpy(), float).reshape(3, 3)
        D = lambda i: np.asarray(i.D.to_numpy(), float).ravel()
        return cls(width=left.width, height=left.height, K_left=K(left), D_left=D(left),
                   T_body_left=pose_matrix(left.T_body_camera),
                   K_right=K(right) if right is not None else None,
                   D_right=D(right) if right is not None else None,
                   T_body_right=pose_matrix(right.T_body_camera) if right is not None else None)


def _rectify(pts: np.ndarray, K: np.ndarray, D: np.ndarray, R: np.ndarray, P: np.ndarray) -> np.ndarray:
    if len(pts) == 0:
        return np.zeros((0, 2))
    out = cv2.undistortPoints(np.asarray(pts, np.float64).reshape(-1, 1, 2), K, D, R=R, P=P)
    return out.reshape(-1, 2)
