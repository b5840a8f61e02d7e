"""The camera driver's logic, free of Zenoh and threads: open the source, read a frame (or a
pair), stamp it, split or convert it, and keep the account a drone engineer checks on the bench:
frames, drops, stalls, re-opens, where the source is and why.

A device that stops delivering (unplugged, a USB reset, a hung pipeline) is closed after
stall_timeout_s and re-opened every reopen_period_s until it answers; a file or folder plays at
rate_hz and ends (or loops). Nothing here raises out of poll(): what goes wrong is a state and a
count.
"""
from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

from aeroperception.services.runtime.config import param

from .capture import CaptureError, Source, StereoPair, describe, open_source, split_side_by_side, to_encoding


@dataclass(frozen=True)
class CameraConfig:
    source: str = param("source")
    source_right: str = param("source_right")
    layout: str = param("layout")
    calibration_path: str = param("calibration_path")
    calibration_path_right: str = param("calibration_path_right")
    calibration_format: str = param("calibration_format")
    rate_hz: float = param("rate_hz")
    width: int = param("width")
    height: int = param("height")
    encoding: str = param("encoding")
    latency_s: float = param("latency_s")
    stall_timeout_s: float = param("stall_timeout_s")
    reopen_period_s: float = param("reopen_period_s")
    loop: bool = param("loop")
    mount_x_m: float = param("mount_x_m")
    mount_y_m: float = param("mount_y_m")
    mount_z_m: float = param("mount_z_m")
    mount_roll_deg: float = param("mount_roll_deg")
    mount_pitch_deg: float = param("mount_pitch_deg")
    mount_yaw_deg: float = param("mount_yaw_deg")


@dataclass
class Frame:
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray | None


class CameraDriver:
    """poll() -> a Frame or None; `state` / `why` / `counts` for diagnostics."""

    def __init__(self, cfg: CameraConfig, open_fn: Callable[..., Source] = open_source,
                 now: Callable[[], float] = time.monotonic, wall_ns: Callable[[], int] = time.time_ns):
        if cfg.layout == "stereo" and not cfg.source_right:
            raise ValueError("layout stereo needs source_right (the right camera's source)")
        if cfg.layout != "stereo" and cfg.source_right:
            raise ValueError(f"source_right is set but layout is {cfg.layout}: it would be ignored")
        self.cfg, self.open_fn, self.now, self.wall_ns = cfg, open_fn, now, wall_ns
        self.source: Source | StereoPair | None = None
        self.counts: Counter[str] = Counter()
        self.state, self.why = "opening", ""
        self.next_open_s = 0.0
        self.last_frame_s: float | None = None
        self.next_due_s: float | None = None
        self.is_file = describe(cfg.source) in ("file", "folder")

    # ------------------------------------------------------------ the loop's questions

    def wait_s(self) -> float:
        """How long the caller may sleep before poll() has something to do (0: poll now)."""
        now = self.now()
        if self.state == "ended":
            return math.inf
        if self.source is None:
            return max(0.0, self.next_open_s - now)
        if self.is_file and self.next_due_s is not None:
            return max(0.0, self.next_due_s - now)
        return 0.0

    def poll(self) -> Frame | None:
        now = self.now()
        if self.state == "ended":
            return None
        if self.source is None and not self._open(now):
            return None
        assert self.source is not None
        try:
            frames = self._read()
        except Exception as e:  # noqa: BLE001 - a backend error is a stall, never the loop's end
            frames = None
            self.why = f"read failed: {type(e).__name__}: {e}"
        if frames is None:
            self._no_frame(now)
            return None
        stamp_ns = self.wall_ns() - int(self.cfg.latency_s * 1e9)
        self._account(now)
        try:
            left, right = self._shape(frames)
        except ValueError as e:
            self.counts["bad_frames"] += 1
            self.why = str(e)
            return None
        self.counts["frames"] += 1
        self.state, self.why = "streaming", ""
        return Frame(stamp_ns, left, right)

    def close(self) -> None:
        if self.source is not None:
            self.source.close()
            self.source = None

    # ------------------------------------------------------------ steps

    def _open(self, now: float) -> bool:
        if now < self.next_open_s:
            return False
        c = self.cfg
        try:
            left = self.open_fn(c.source, c.width, c.height, c.rate_hz)
            self.source = StereoPair(left, self.open_fn(c.source_right, c.width, c.height, c.rate_hz)) \
                if c.layout == "stereo" else left
        except CaptureError as e:
            self.counts["open_failures"] += 1
            self.state, self.why = "failed", str(e)
            self.next_open_s = now + c.reopen_period_s
            return False
        self.counts["opens"] += 1
        self.last_frame_s, self.next_due_s = now, None
        if self.state != "opening":
            self.counts["reopens"] += 1
        self.state = "waiting"
        return True

    def _read(self) -> tuple[np.ndarray, np.ndarray | None] | None:
        src = self.source
        if isinstance(src, StereoPair):
            return src.read_pair()
        frame = src.read() if src is not None else None
        return None if frame is None else (frame, None)

    def _no_frame(self, now: float) -> None:
        src = self.source
        if src is not None and src.ended:
            self.close()
            if self.cfg.loop:
                self.counts["loops"] += 1
                self.next_open_s = now
                self.state = "opening"
            else:
                self.state, self.why = "ended", f"{self.cfg.source}: end of the recording"
            return
        assert self.last_frame_s is not None
        if now - self.last_frame_s > self.cfg.stall_timeout_s:
            self.counts["stalls"] += 1
            self.why = f"no frame for {now - self.last_frame_s:.1f} s: re-opening" + (f" ({self.why})" if self.why else "")
            self.state = "stalled"
            self.close()
            self.next_open_s = now

    def _account(self, now: float) -> None:
        """Frame drops of a device: an interval of more than 1.5 periods lost the frames between."""
        if self.is_file:
            period = 1.0 / self.cfg.rate_hz
            self.next_due_s = (self.next_due_s or now) + period
            if self.next_due_s < now - period:        # fell behind (a loaded host): never a burst to catch up
                self.counts["late"] += 1
                self.next_due_s = now + period
        elif self.last_frame_s is not None and self.counts["frames"]:
            gap = (now - self.last_frame_s) * self.cfg.rate_hz
            if gap > 1.5:
                self.counts["dropped"] += int(round(gap)) - 1
        self.last_frame_s = now

    def _shape(self, frames: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, np.ndarray | None]:
        left, right = frames
        if self.cfg.layout == "side_by_side":
            left, right = split_side_by_side(left)
        enc = self.cfg.encoding
        return to_encoding(left, enc), (to_encoding(right, enc) if right is not None else None)
