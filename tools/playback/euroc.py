"""An EuRoC / ASL folder as the message stream a stereo camera, its IMU and a motion-capture truth
would put on Zenoh: `sensors/camera/{left,right}/image` (mono8, stamped at exposure),
`sensors/camera/{left,right}/info` (the folder's calibration with the body <- camera extrinsics,
once a second and with the first frame), `sensors/imu` and the recording's ground truth on
`sim/truth/state` (what `aero eval vio --live` scores against), in time order.

The body frame is the dataset's IMU frame (EuRoC's body: the estimators' and the truth's), so the
extrinsics and the truth need no conversion. Images are read from disk only when their turn comes:
a long sequence streams in constant memory.
"""
from __future__ import annotations

import heapq
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import msgspec
import numpy as np

from aeroperception.schemas import CameraInfo, Header, Image, Imu, Quaternion, Vector3, VehicleState, encode
from aeroperception.services.recorder.replay import Recorded
from aeroperception.services.runtime.node import encoding_for
from aeroperception.services.vio.euroc import EurocDataset

IMAGE_KEYS = {"cam0": "sensors/camera/left/image", "cam1": "sensors/camera/right/image"}
INFO_KEYS = {"cam0": "sensors/camera/left/info", "cam1": "sensors/camera/right/info"}
IMU_KEY = "sensors/imu"
TRUTH_KEY = "sim/truth/state"
INFO_PERIOD_NS = 1_000_000_000


class PlaybackError(ValueError):
    """The folder or the window asked for cannot be played (said in one line)."""


@dataclass(frozen=True)
class Window:
    """The part of the recording to play, in seconds from its first camera frame."""

    start_s: float = 0.0
    duration_s: float | None = None


class EurocPlayback:
    """What `aero play euroc DIR` publishes, as Recorded messages in stamp order."""

    def __init__(self, root: str | Path, window: Window = Window(), truth: bool = True, prefix: str = ""):
        root = Path(root)
        if not (root / "mav0" / "cam0").is_dir():
            raise PlaybackError(f"{root}: not an EuRoC/ASL folder (no mav0/cam0)")
        self.ds = EurocDataset(root)
        self.prefix = prefix
        self.infos = {cam: info for cam, info in zip(("cam0", "cam1"), self.ds.camera_infos()) if info is not None}
        frames = self.ds.frame_stamps_ns
        if len(frames) == 0:
            raise PlaybackError(f"{root}: no camera frames in mav0/cam0/data.csv")
        t0 = int(frames[0]) + int(window.start_s * 1e9)
        t1 = t0 + int(window.duration_s * 1e9) if window.duration_s is not None else int(frames[-1])
        self.frames = frames[(frames >= t0) & (frames <= t1)]
        if len(self.frames) == 0:
            raise PlaybackError(f"{root}: no camera frame in the window ({window.start_s:g} s + "
                                f"{window.duration_s} s; the recording has {(frames[-1] - frames[0]) * 1e-9:.1f} s)")
        self.t0_ns, self.t1_ns = int(self.frames[0]), int(self.frames[-1])
        self.truth = truth and self.ds.groundtruth is not None

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9

    def info(self, cam: str, stamp_ns: int) -> CameraInfo:
        info = self.infos[cam]
        return msgspec.structs.replace(info, header=Header(stamp_ns=stamp_ns, frame_id=info.header.frame_id))

    def messages(self) -> Iterator[Recorded]:
        """Every message of the window, merged by stamp (IMU from 0.5 s before the first frame,
        so an estimator initialises on the first image)."""
        streams = [self._cameras(), self._imu(self.t0_ns - 500_000_000)]
        if self.truth:
            streams.append(self._truth())
        return heapq.merge(*streams, key=lambda r: r.log_time_ns)

    # ---------------------------------------------------------------- streams

    def _rec(self, key: str, msg, t_ns: int) -> Recorded:
        return Recorded(self.prefix + key, str(encoding_for(type(msg))), encode(msg), t_ns)

    def _cameras(self) -> Iterator[Recorded]:
        last_info = None
        for t in self.frames:
            t = int(t)
            if last_info is None or t - last_info >= INFO_PERIOD_NS:
                last_info = t
                for cam in self.infos:
                    yield self._rec(INFO_KEYS[cam], self.info(cam, t), t)
            for cam in self.infos:
                path = self.ds.image_path(cam, t)
                pixels = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
                if pixels is None:
                    raise PlaybackError(f"{path}: missing or not an image")
                frame = self.infos[cam].header.frame_id
                yield self._rec(IMAGE_KEYS[cam], Image.from_numpy(pixels, "mono8", Header(stamp_ns=t, frame_id=frame)), t)

    def _imu(self, from_ns: int) -> Iterator[Recorded]:
        a, ts = self.ds.imu_array, self.ds.imu_t_ns
        for i in np.flatnonzero((ts >= from_ns) & (ts <= self.t1_ns)):
            t = int(ts[i])
            yield self._rec(IMU_KEY, Imu(header=Header(stamp_ns=t, frame_id="base_link"),
                                         angular_velocity_radps=Vector3.from_array(a[i, 1:4]),
                                         linear_acceleration_mps2=Vector3.from_array(a[i, 4:7])), t)

    def _truth(self) -> Iterator[Recorded]:
        gt = self.ds.groundtruth
        assert gt is not None
        for i in np.flatnonzero((gt.t_ns >= self.t0_ns - 500_000_000) & (gt.t_ns <= self.t1_ns)):
            t = int(gt.t_ns[i])
            yield self._rec(TRUTH_KEY, VehicleState(
                header=Header(stamp_ns=t, frame_id="world"), position_m=Vector3.from_array(gt.position_m[i]),
                velocity_mps=Vector3.from_array(gt.velocity_mps[i]),
                orientation=Quaternion.from_array(gt.q_wxyz[i]), estimator_name="groundtruth",
                confidence=1.0), t)
