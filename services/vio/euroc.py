"""EuRoC / ASL dataset folder reader: stereo image list, IMU, ground truth and the sensor.yaml
calibration as the same CameraInfo messages a live camera driver publishes (so the VIO reads a
dataset through its normal calibration path).

Layout: <dir>/mav0/{cam0,cam1}/{data.csv,data/*.png,sensor.yaml}, imu0/{data.csv,sensor.yaml},
state_groundtruth_estimate0/data.csv (optional). cam0 is the left camera.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterator

import numpy as np
import yaml

from aeroperception.schemas import CameraInfo, Header, NDArray, Pose, Quaternion, Vector3
from aeroperception.services.runtime.data import shared_data_dir
from aeroperception.services.runtime.rotations import quat_from_rotmat

from .dto import ImuSample
from .imu import ImuNoise


def default_euroc_dir() -> Path | None:
    d = shared_data_dir()
    cand = d / "euroc" / "V1_01_easy_start" if d else None
    return cand if cand is not None and (cand / "mav0").is_dir() else None


def _read_yaml(path: Path) -> dict:
    text = path.read_text()
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1]   # OpenCV's header; PyYAML rejects version 1.0 directives
    return yaml.safe_load(text)


def _csv(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64, ndmin=2)


@dataclass
class GroundTruth:
    t_ns: np.ndarray          # (N,) int64
    position_m: np.ndarray    # (N, 3) body (IMU) origin in the world
    q_wxyz: np.ndarray        # (N, 4) world <- body
    velocity_mps: np.ndarray  # (N, 3)
    gyro_bias_radps: np.ndarray
    accel_bias_mps2: np.ndarray

    def index_at(self, t_ns: int) -> int:
        """Index of the sample nearest to t_ns."""
        i = int(np.searchsorted(self.t_ns, t_ns))
        if i == 0:
            return 0
        if i >= len(self.t_ns):
            return len(self.t_ns) - 1
        return i if self.t_ns[i] - t_ns < t_ns - self.t_ns[i - 1] else i - 1


class EurocDataset:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.mav = self.root / "mav0"
        if not (self.mav / "cam0" / "data.csv").is_file():
            raise FileNotFoundError(f"{self.root} is not an EuRoC/ASL folder (no mav0/cam0/data.csv)")

    # -------------------------------------------------------------- cameras

    @cached_property
    def frame_stamps_ns(self) -> np.ndarray:
        """Stamps present in both cam0 and cam1 (stereo pairs), sorted."""
        left = self._stamps("cam0")
        right = set(self._stamps("cam1").tolist()) if (self.mav / "cam1" / "data.csv").is_file() else None
        return np.array([t for t in left if right is None or t in right], dtype=np.int64)

    def _stamps(self, cam: str) -> np.ndarray:
        rows = [ln.split(",")[0] for ln in (self.mav / cam / "data.csv").read_text().splitlines()
                if ln and not ln.startswith("#")]
        return np.array(sorted(int(r) for r in rows), dtype=np.int64)

    def image_path(self, cam: str, t_ns: int) -> Path:
        return self.mav / cam / "data" / f"{t_ns}.png"

    def load_pair(self, t_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
        import cv2

        left = cv2.imread(str(self.image_path("cam0", t_ns)), cv2.IMREAD_GRAYSCALE)
        if left is None:
            raise FileNotFoundError(self.image_path("cam0", t_ns))
        rp = self.image_path("cam1", t_ns)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE) if rp.is_file() else None
        return left, right

    def pairs(self) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
        for t in self.frame_stamps_ns:
            left, right = self.load_pair(int(t))
            yield int(t), left, right

    def camera_info(self, cam: str = "cam0") -> CameraInfo:
        y = _read_yaml(self.mav / cam / "sensor.yaml")
        model = y.get("distortion_model", "radial-tangential")
        if model not in ("radial-tangential", "radtan", "plumb_bob"):
            raise ValueError(f"{cam}: distortion model {model!r} not supported (radial-tangential only)")
        fu, fv, cu, cv = y["intrinsics"]
        w, h = y["resolution"]
        T = np.array(y["T_BS"]["data"], float).reshape(4, 4)
        K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
        frame = "camera_left_optical" if cam == "cam0" else "camera_right_optical"
        return CameraInfo(header=Header(stamp_ns=int(self.frame_stamps_ns[0]), frame_id=frame),
                          width=int(w), height=int(h), distortion_model="plumb_bob",
                          K=NDArray.from_numpy(K), D=NDArray.from_numpy(np.array(y["distortion_coefficients"], float)),
                          P=NDArray.from_numpy(np.hstack([K, np.zeros((3, 1))])),
                          T_body_camera=Pose(position=Vector3.from_array(T[:3, 3]),
                                             orientation=Quaternion.from_array(quat_from_rotmat(T[:3, :3]))))

    def camera_infos(self) -> tuple[CameraInfo, CameraInfo | None]:
        right = self.camera_info("cam1") if (self.mav / "cam1" / "sensor.yaml").is_file() else None
        return self.camera_info("cam0"), right

    # -------------------------------------------------------------- IMU, truth

    @cached_property
    def imu_array(self) -> np.ndarray:
        """(N, 7): t_ns, gyro xyz rad/s, accel xyz m/s^2 (the IMU is the body frame)."""
        a = _csv(self.mav / "imu0" / "data.csv")
        return a[np.argsort(a[:, 0], kind="stable")]

    @cached_property
    def imu_t_ns(self) -> np.ndarray:
        return self.imu_array[:, 0].astype(np.int64)

    def imu_samples(self, t0_ns: int | None = None, t1_ns: int | None = None) -> list[ImuSample]:
        """Samples with t0 < t <= t1 (all when None)."""
        t = self.imu_t_ns
        lo = 0 if t0_ns is None else int(np.searchsorted(t, t0_ns, side="right"))
        hi = len(t) if t1_ns is None else int(np.searchsorted(t, t1_ns, side="right"))
        a = self.imu_array
        return [ImuSample(int(t[i]), a[i, 1:4].copy(), a[i, 4:7].copy()) for i in range(lo, hi)]

    def imu_noise(self) -> ImuNoise:
        y = _read_yaml(self.mav / "imu0" / "sensor.yaml")
        return ImuNoise(gyro_noise_density=float(y["gyroscope_noise_density"]),
                        accel_noise_density=float(y["accelerometer_noise_density"]),
                        gyro_random_walk=float(y["gyroscope_random_walk"]),
                        accel_random_walk=float(y["accelerometer_random_walk"]))

    @cached_property
    def groundtruth(self) -> GroundTruth | None:
        p = self.mav / "state_groundtruth_estimate0" / "data.csv"
        if not p.is_file():
            return None
        a = _csv(p)
        a = a[np.argsort(a[:, 0], kind="stable")]
        return GroundTruth(t_ns=a[:, 0].astype(np.int64), position_m=a[:, 1:4], q_wxyz=a[:, 4:8],
                           velocity_mps=a[:, 8:11], gyro_bias_radps=a[:, 11:14], accel_bias_mps2=a[:, 14:17])
