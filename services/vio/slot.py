"""Stereo pairing and the one-frame slot between the Zenoh callbacks and the VIO worker.

Images arrive on two keys; a pair is a left and a right with the same stamp. The worker takes
one pair at a time; a pair completed while the worker is busy replaces the waiting one (newest
wins: the VIO must stay current, a late frame is worth less than the next) and the replaced pair
is counted as dropped. A left image replaced before its right one came is counted as unpaired.
Thread-safe; `take` blocks up to a timeout.
"""
from __future__ import annotations

import threading
from typing import Any


class FrameSlot:
    def __init__(self, stereo: bool = True):
        self.stereo = stereo
        self._cond = threading.Condition()
        self._latest: dict[str, Any] = {"left": None, "right": None}
        self._slot: tuple[Any, Any] | None = None
        self.frames_in = self.dropped = self.unpaired = 0

    def put(self, side: str, image: Any, stamp_ns: int) -> None:
        with self._cond:
            if side == "left":
                self.frames_in += 1
                if self._latest["left"] is not None:
                    self.unpaired += 1
            self._latest[side] = (image, stamp_ns)
            left, right = self._latest["left"], self._latest["right"]
            if left is None:
                return
            if self.stereo and (right is None or right[1] != left[1]):
                return
            self._latest = {"left": None, "right": None}
            if self._slot is not None:
                self.dropped += 1
            self._slot = (left[0], right[0] if self.stereo else None)
            self._cond.notify()

    def take(self, timeout_s: float) -> tuple[Any, Any] | None:
        """The waiting pair (left, right or None), or None after timeout_s."""
        with self._cond:
            self._cond.wait_for(lambda: self._slot is not None, timeout=timeout_s)
            pair, self._slot = self._slot, None
            return pair

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()


class ImuWatermark:
    """The newest IMU stamp received, which the worker waits on before a frame: under load the IMU
    callbacks can run behind the image callbacks (both need the interpreter), and a frame processed
    before the samples up to its stamp are in gets an IMU gap for the samples still queued (they
    arrive after and are never integrated). Waiting is bounded: a truly missing IMU stays a gap."""

    def __init__(self):
        self._cond = threading.Condition()
        self.newest_ns = 0
        self.waits = self.timeouts = 0

    def put(self, stamp_ns: int) -> None:
        with self._cond:
            if stamp_ns > self.newest_ns:
                self.newest_ns = stamp_ns
                self._cond.notify_all()

    def wait_for(self, stamp_ns: int, timeout_s: float) -> bool:
        """True once a sample at or after `stamp_ns` is in; False after `timeout_s` without one."""
        with self._cond:
            if self.newest_ns >= stamp_ns:
                return True
            self.waits += 1
            if self._cond.wait_for(lambda: self.newest_ns >= stamp_ns, timeout_s):
                return True
            self.timeouts += 1
            return False
