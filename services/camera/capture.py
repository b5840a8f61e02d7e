"""Where frames come from, free of Zenoh: a V4L2/UVC device, a GStreamer pipeline, a video file
(OpenCV's VideoCapture: one code path, the argument differs) or a folder of images; mono, two
devices grabbed together, or one side-by-side frame split in two.

A source says what happened in one word instead of raising: a frame, no frame yet (`None`), or
the end of a file (`ended`). Stalls, re-opening and pacing are the driver's (driver.py).
"""
from __future__ import annotations

from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mjpeg", ".mjpg")


class CaptureError(RuntimeError):
    """The source cannot be opened (said in one line, naming it)."""


class Source(Protocol):
    ended: bool          # a file or folder has no more frames (a device never ends)
    is_file: bool        # paced by the driver at rate_hz (a device paces itself)

    def read(self) -> np.ndarray | None: ...
    def close(self) -> None: ...


def describe(spec: str) -> str:
    """What kind of source `spec` names: device, gstreamer, file, folder."""
    if spec.startswith("gst:"):
        return "gstreamer"
    if spec.isdigit() or spec.startswith("/dev/"):
        return "device"
    return "folder" if Path(spec).is_dir() else "file"


def open_source(spec: str, width: int = 0, height: int = 0, rate_hz: float = 0.0) -> Source:
    kind = describe(spec)
    if kind == "folder":
        return FolderSource(Path(spec))
    return VideoSource(spec, kind, width, height, rate_hz)


class VideoSource:
    """cv2.VideoCapture over a device (/dev/videoN or its index), a GStreamer pipeline
    ("gst:" + the pipeline, ending in appsink) or a video file."""

    def __init__(self, spec: str, kind: str, width: int = 0, height: int = 0, rate_hz: float = 0.0):
        self.spec, self.kind = spec, kind
        self.is_file = kind == "file"
        self.ended = False
        if kind == "gstreamer":
            self.cap = cv2.VideoCapture(spec[4:], cv2.CAP_GSTREAMER)
        elif kind == "device":
            self.cap = cv2.VideoCapture(int(spec) if spec.isdigit() else spec, cv2.CAP_V4L2)
        else:
            if not Path(spec).is_file():
                raise CaptureError(f"{spec}: no such file, folder or device")
            self.cap = cv2.VideoCapture(spec)
        if not self.cap.isOpened():
            why = " (this OpenCV has no GStreamer)" if kind == "gstreamer" and "GStreamer:                   NO" in \
                cv2.getBuildInformation() else ""
            raise CaptureError(f"{spec}: OpenCV cannot open this {kind}{why}")
        if kind == "device":
            if width and height:
                self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
                self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            if rate_hz:
                self.cap.set(cv2.CAP_PROP_FPS, rate_hz)

    def grab(self) -> bool:
        ok = self.cap.grab()
        if not ok and self.is_file:
            self.ended = True
        return ok

    def retrieve(self) -> np.ndarray | None:
        ok, frame = self.cap.retrieve()
        return frame if ok else None

    def read(self) -> np.ndarray | None:
        return self.retrieve() if self.grab() else None

    def close(self) -> None:
        self.cap.release()


class FolderSource:
    """The images of a folder in name order (EuRoC's cam0/data, a camera's dump)."""

    is_file = True

    def __init__(self, folder: Path):
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise CaptureError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
        self.i = 0
        self.ended = False
        self.unreadable = 0

    def read(self) -> np.ndarray | None:
        while self.i < len(self.files):
            path = self.files[self.i]
            self.i += 1
            frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if frame is not None:
                return frame
            self.unreadable += 1                 # skipped, counted in the driver's health
        self.ended = True
        return None

    def close(self) -> None:
        pass


class StereoPair:
    """Two sources read as one: both grabbed before either is decoded, so the pair is as close
    in time as the devices allow; a file pair ends when either does."""

    def __init__(self, left: Source, right: Source):
        self.left, self.right = left, right
        self.is_file = left.is_file

    @property
    def ended(self) -> bool:
        return self.left.ended or self.right.ended

    def read_pair(self) -> tuple[np.ndarray, np.ndarray] | None:
        if isinstance(self.left, VideoSource) and isinstance(self.right, VideoSource):
            if not (self.left.grab() and self.right.grab()):
                return None
            a, b = self.left.retrieve(), self.right.retrieve()
        else:
            a, b = self.left.read(), self.right.read()
        return None if a is None or b is None else (a, b)

    def close(self) -> None:
        self.left.close()
        self.right.close()


def split_side_by_side(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One frame holding left | right (a ZED, an ELP stereo USB camera) into the two images."""
    w = frame.shape[1]
    if w % 2:
        raise ValueError(f"a side-by-side frame must be an even width, not {w}")
    return frame[:, : w // 2], frame[:, w // 2:]


def to_encoding(frame: np.ndarray, encoding: str) -> np.ndarray:
    """An OpenCV frame (BGR, BGRA or grey; 8 or 16 bit) as `encoding` (mono8, mono16, rgb8, bgr8)."""
    grey = frame.ndim == 2 or frame.shape[2] == 1
    if frame.dtype == np.uint16 and encoding != "mono16":
        frame = (frame >> 8).astype(np.uint8)
    if encoding in ("mono8", "mono16"):
        out = frame if grey else cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        out = out.reshape(out.shape[:2])
        if encoding == "mono16" and out.dtype != np.uint16:
            out = out.astype(np.uint16) << 8
        return np.ascontiguousarray(out)
    if grey:
        frame = cv2.cvtColor(frame.reshape(frame.shape[:2]), cv2.COLOR_GRAY2BGR)
    elif frame.shape[2] == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(frame if encoding == "bgr8" else cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
