"""A camera's (or a stereo pair's) calibration from the files the usual tools write, as the
CameraInfo messages the stack reads: OpenCV FileStorage YAML (calibrateCamera / stereoCalibrate:
camera_matrix + distortion_coefficients, or M1 D1 M2 D2 R T), Kalibr's camchain YAML (cam0, cam1
with T_cam_imu and T_cn_cnm1) and ROS camera_info YAML (camera_calibration's ost.yaml; one file
per camera).

Extrinsics body <- camera: Kalibr's T_cam_imu places the cameras on the IMU, which is the body
(the FC's IMU frame). The other formats do not say where the camera sits: the driver's mount
parameters give the left camera, the stereo calibration the right one from the left. Only the
radial-tangential (plumb_bob) model is read; any other is refused by name, never half-read.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from aeroperception.schemas import CameraInfo, Header, NDArray, Pose, Quaternion, Vector3
from aeroperception.services.runtime.rotations import quat_from_rotmat

FORMATS = ("auto", "opencv", "kalibr", "ros")
RADTAN = ("radtan", "radial-tangential", "plumb_bob")


class CalibrationError(ValueError):
    """The file cannot be read as a calibration (said in one line, naming the file and field)."""


@dataclass
class Calibration:
    """The intrinsics of one or two cameras and what the file says of their extrinsics."""

    left: CameraInfo
    right: CameraInfo | None = None
    t_body_left: np.ndarray | None = None      # 4x4 body <- left optical, when the file places it (Kalibr)
    t_left_right: np.ndarray | None = None     # 4x4 left optical <- right optical (stereo files)
    fmt: str = ""

    def infos(self, t_body_left: np.ndarray) -> tuple[CameraInfo, CameraInfo | None]:
        """Both infos with T_body_camera filled: `t_body_left` (the file's, else the mount's)."""
        left = _with_pose(self.left, t_body_left)
        if self.right is None:
            return left, None
        t_lr = self.t_left_right if self.t_left_right is not None else np.eye(4)
        return left, _with_pose(self.right, t_body_left @ t_lr)


def load(path: str | Path, fmt: str = "auto", right_path: str | Path | None = None,
         size: tuple[int, int] | None = None) -> Calibration:
    """Read `path` (and `right_path`: the right camera's ROS camera_info file) as `fmt`.
    `size` (width, height): the image size when an OpenCV file lacks it."""
    path = Path(path)
    if fmt not in FORMATS:
        raise CalibrationError(f"calibration format {fmt!r}: one of {', '.join(FORMATS)}")
    try:
        text = path.read_text()
    except OSError as e:
        raise CalibrationError(f"{path}: {e.strerror or e}") from None
    if fmt == "auto":
        fmt = _detect(path, text)
    try:
        if fmt == "kalibr":
            return _kalibr(_yaml(path, text))
        if fmt == "ros":
            cal = Calibration(_ros(path, _yaml(path, text)), fmt="ros")
            if right_path:
                rp = Path(right_path)
                cal.right = _ros(rp, _yaml(rp, rp.read_text()))
                cal.t_left_right = _ros_baseline(cal.left, cal.right)
            return cal
        return _opencv(path, size)
    except CalibrationError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, cv2.error, OSError) as e:
        raise CalibrationError(f"{path}: not a {fmt} calibration ({type(e).__name__}: {e})") from None


def _detect(path: Path, text: str) -> str:
    if text.lstrip().startswith("%YAML:1.0") or "opencv-matrix" in text:
        return "opencv"
    data = _yaml(path, text)
    if isinstance(data, dict) and "cam0" in data:
        return "kalibr"
    if isinstance(data, dict) and "camera_matrix" in data and "image_width" in data:
        return "ros"
    raise CalibrationError(f"{path}: neither OpenCV FileStorage, Kalibr camchain nor ROS camera_info YAML")


def _yaml(path: Path, text: str) -> dict:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise CalibrationError(f"{path}: not YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: not a YAML mapping")
    return data


def _info(width: int, height: int, K, D, frame_id: str, R=None, P=None, model: str = "plumb_bob") -> CameraInfo:
    if model not in RADTAN:
        raise CalibrationError(f"distortion model {model!r} is not read (radial-tangential / plumb_bob only)")
    K = np.asarray(K, float).reshape(3, 3)
    D = np.asarray(D, float).ravel()
    if width <= 0 or height <= 0:
        raise CalibrationError(f"image size {width}x{height}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"focal lengths {K[0, 0]}, {K[1, 1]} must be > 0")
    P = np.hstack([K, np.zeros((3, 1))]) if P is None else np.asarray(P, float).reshape(3, 4)
    R = np.eye(3) if R is None else np.asarray(R, float).reshape(3, 3)
    return CameraInfo(header=Header(frame_id=frame_id), width=int(width), height=int(height), distortion_model="plumb_bob",
                      K=NDArray.from_numpy(K), D=NDArray.from_numpy(D), R=NDArray.from_numpy(R), P=NDArray.from_numpy(P))


def _with_pose(info: CameraInfo, t_body_camera: np.ndarray) -> CameraInfo:
    import msgspec

    return msgspec.structs.replace(info, T_body_camera=Pose(
        position=Vector3.from_array(t_body_camera[:3, 3]),
        orientation=Quaternion.from_array(quat_from_rotmat(t_body_camera[:3, :3]))))


def _inv(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def _transform(data, what: str) -> np.ndarray:
    t = np.asarray(data, float)
    if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]) or not np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-3):
        raise CalibrationError(f"{what} is not a 4x4 rigid transform")
    return t


def _kalibr(data: dict) -> Calibration:
    cams = []
    for name in ("cam0", "cam1"):
        c = data.get(name)
        if c is None:
            break
        if c.get("camera_model", "pinhole") != "pinhole":
            raise CalibrationError(f"{name}: camera_model {c['camera_model']!r} (pinhole only)")
        fu, fv, pu, pv = c["intrinsics"]
        w, h = c["resolution"]
        cams.append((c, _info(w, h, [[fu, 0, pu], [0, fv, pv], [0, 0, 1]], c["distortion_coeffs"],
                              "camera_left_optical" if name == "cam0" else "camera_right_optical",
                              model=c.get("distortion_model", "radtan"))))
    if not cams:
        raise CalibrationError("no cam0 in the camchain")
    c0, left = cams[0]
    cal = Calibration(left, fmt="kalibr")
    if "T_cam_imu" in c0:
        cal.t_body_left = _inv(_transform(c0["T_cam_imu"], "cam0.T_cam_imu"))
    if len(cams) > 1:
        c1, cal.right = cams[1]
        if "T_cn_cnm1" in c1:
            cal.t_left_right = _inv(_transform(c1["T_cn_cnm1"], "cam1.T_cn_cnm1"))
        elif "T_cam_imu" in c1 and cal.t_body_left is not None:
            cal.t_left_right = _inv(cal.t_body_left) @ _inv(_transform(c1["T_cam_imu"], "cam1.T_cam_imu"))
        else:
            raise CalibrationError("cam1 has neither T_cn_cnm1 nor T_cam_imu: where it sits is unknown")
    return cal


def _matrix(d: dict, key: str) -> np.ndarray:
    m = d[key]
    return np.asarray(m["data"], float).reshape(int(m["rows"]), int(m["cols"]))


def _ros(path: Path, d: dict) -> CameraInfo:
    return _info(int(d["image_width"]), int(d["image_height"]), _matrix(d, "camera_matrix"),
                 _matrix(d, "distortion_coefficients"), "camera_right_optical" if "right" in str(d.get("camera_name", ""))
                 else "camera_left_optical", _matrix(d, "rectification_matrix") if "rectification_matrix" in d else None,
                 _matrix(d, "projection_matrix") if "projection_matrix" in d else None,
                 model=d.get("distortion_model", "plumb_bob"))


def _ros_baseline(left: CameraInfo, right: CameraInfo) -> np.ndarray:
    """left <- right of a ROS stereo pair: both rectified (R) onto a common plane where the right
    camera sits at Tx = -fx * baseline along x (its projection matrix)."""
    p = right.P.to_numpy()
    baseline = -p[0, 3] / p[0, 0]
    rect = np.eye(4)
    rect[0, 3] = baseline
    r_l, r_r = np.eye(4), np.eye(4)
    r_l[:3, :3], r_r[:3, :3] = left.R.to_numpy().T, right.R.to_numpy().T
    return r_l @ rect @ _inv(r_r)


def _opencv(path: Path, size: tuple[int, int] | None) -> Calibration:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: OpenCV cannot open it as FileStorage")
    try:
        def mat(*names: str) -> np.ndarray | None:
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return node.mat()
            return None

        def num(*names: str) -> int:
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return int(node.real())
            return 0

        w, h = num("image_width", "width"), num("image_height", "height")
        if (w <= 0 or h <= 0) and size:
            w, h = size
        if w <= 0 or h <= 0:
            raise CalibrationError(f"{path}: no image_width / image_height (give the camera's width and height)")
        k1, d1 = mat("camera_matrix", "M1", "K1"), mat("distortion_coefficients", "D1")
        if k1 is None or d1 is None:
            raise CalibrationError(f"{path}: no camera_matrix / distortion_coefficients (or M1 / D1)")
        cal = Calibration(_info(w, h, k1, d1, "camera_left_optical"), fmt="opencv")
        k2, d2 = mat("M2", "K2"), mat("D2")
        if k2 is not None and d2 is not None:
            r, t = mat("R"), mat("T")
            if r is None or t is None:
                raise CalibrationError(f"{path}: M2 / D2 without R / T: where the right camera sits is unknown")
            right_T_left = np.eye(4)
            right_T_left[:3, :3], right_T_left[:3, 3] = r, np.asarray(t, float).ravel()
            cal.right = _info(w, h, k2, d2, "camera_right_optical")
            cal.t_left_right = _inv(_transform(right_T_left, "R, T"))
        return cal
    finally:
        fs.release()
