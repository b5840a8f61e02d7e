"""The camera driver's loop logic on real frames (the EuRoC MH_01 clip's image folder) and on a
device that stalls: pacing, the end of a recording and looping, stall -> re-open, drops counted,
side-by-side split, encodings; nothing raises out of poll()."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from aeroperception.services.camera import contract
from aeroperception.services.camera.capture import CaptureError, FolderSource, split_side_by_side, to_encoding
from aeroperception.services.camera.driver import CameraConfig, CameraDriver
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.data import shared_data_dir

DATA = shared_data_dir()
CAM0 = DATA / "euroc" / "MH_01_clip" / "mav0" / "cam0" / "data" if DATA else None
pytestmark = pytest.mark.skipif(CAM0 is None or not CAM0.is_dir(), reason="../shared/data absent")


def config(**kw) -> CameraConfig:
    return build(CameraConfig, contract.PARAMS, **kw)


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Device:
    """A device as OpenCV sees one: frames until it stalls (read() gives nothing), then nothing."""

    is_file, ended = False, False

    def __init__(self, frames: int, log: list):
        self.left, self.log = frames, log
        log.append("open")

    def read(self):
        if self.left <= 0:
            return None
        self.left -= 1
        return np.zeros((4, 6, 3), np.uint8)

    def close(self):
        self.log.append("close")


def test_a_folder_plays_at_its_rate_and_ends_saying_so():
    clock = Clock()
    d = CameraDriver(config(source=str(CAM0), rate_hz=20.0), now=clock, wall_ns=lambda: int(clock.t * 1e9))
    frames = []
    for _ in range(1000):
        wait = d.wait_s()
        if wait == np.inf:
            break
        clock.t += wait
        f = d.poll()
        if f is not None:
            frames.append(f)
    assert len(frames) == 240 and d.state == "ended" and "end of the recording" in d.why
    stamps = np.diff([f.stamp_ns for f in frames]) * 1e-9
    np.testing.assert_allclose(stamps, 0.05, atol=1e-6)          # paced at 20 Hz
    assert frames[0].left.shape == (480, 752) and frames[0].left.dtype == np.uint8 and frames[0].right is None
    ref = cv2.imread(str(sorted(CAM0.iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(frames[0].left, ref)


def test_a_looping_folder_starts_again():
    clock = Clock()
    d = CameraDriver(config(source=str(CAM0), loop=True, rate_hz=100.0), now=clock)
    n = 0
    for _ in range(600):
        clock.t += d.wait_s()
        n += d.poll() is not None
    assert d.counts["loops"] == 2 and n > 480 and d.state == "streaming"


def test_a_stalled_device_is_closed_and_reopened_and_its_drops_counted():
    clock, log = Clock(), []
    opened = []

    def open_fn(spec, *_):
        opened.append(spec)
        return Device(3, log)

    d = CameraDriver(config(source="/dev/video9", stall_timeout_s=1.0, rate_hz=20.0), open_fn=open_fn, now=clock)
    assert d.poll() is not None                      # opened, a frame
    clock.t += 0.05
    assert d.poll() is not None
    clock.t += 0.20                                  # three frames lost in between
    assert d.poll() is not None and d.counts["dropped"] == 3
    clock.t += 0.5
    assert d.poll() is None and d.state == "streaming"        # nothing yet: not stalled before 1 s
    clock.t += 0.6
    assert d.poll() is None and d.state == "stalled" and "no frame for 1.1 s" in d.why and log[-1] == "close"
    assert d.poll() is not None and d.counts["reopens"] == 1 and opened == ["/dev/video9"] * 2


def test_a_device_that_will_not_open_is_retried_every_period():
    clock, tries = Clock(), []

    def open_fn(spec, *_):
        tries.append(clock.t)
        raise CaptureError(f"{spec}: OpenCV cannot open this device")

    d = CameraDriver(config(source="/dev/video9", reopen_period_s=2.0), open_fn=open_fn, now=clock)
    for _ in range(50):
        clock.t += 0.25
        assert d.poll() is None
    assert d.state == "failed" and "cannot open" in d.why and len(tries) == 7 and d.counts["open_failures"] == 7


def test_a_read_that_raises_is_a_stall_not_a_crash():
    clock = Clock()

    class Broken(Device):
        def read(self):
            raise cv2.error("backend died")

    d = CameraDriver(config(source="/dev/video9", stall_timeout_s=0.5), open_fn=lambda *_: Broken(0, []), now=clock)
    assert d.poll() is None
    clock.t += 1.0
    assert d.poll() is None and d.state == "stalled" and "backend died" in d.why


def test_stereo_layouts_say_what_they_lack():
    with pytest.raises(ValueError, match="needs source_right"):
        CameraDriver(config(layout="stereo"))
    with pytest.raises(ValueError, match="source_right is set but layout is mono"):
        CameraDriver(config(source_right="/dev/video1"))


def test_two_folders_are_a_stereo_pair_frame_by_frame():
    clock = Clock()
    d = CameraDriver(config(source=str(CAM0), source_right=str(CAM0.parent.parent / "cam1" / "data"), layout="stereo"),
                     now=clock)
    f = d.poll()
    right = cv2.imread(str(sorted((CAM0.parent.parent / "cam1" / "data").iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    assert f is not None and f.right is not None
    np.testing.assert_array_equal(f.right, right)


def test_side_by_side_and_encodings():
    img = cv2.imread(str(sorted(CAM0.iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    both = np.hstack([img, img[:, ::-1]])
    left, right = split_side_by_side(both)
    np.testing.assert_array_equal(left, img)
    np.testing.assert_array_equal(right, img[:, ::-1])
    with pytest.raises(ValueError, match="even width"):
        split_side_by_side(both[:, :-1])
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    assert to_encoding(bgr, "mono8").shape == img.shape
    assert to_encoding(img, "rgb8").shape == (*img.shape, 3)
    assert to_encoding(img, "mono16").dtype == np.uint16
    np.testing.assert_array_equal(to_encoding(bgr, "bgr8"), bgr)


def test_an_unreadable_image_in_a_folder_is_skipped_and_counted(tmp_path):
    (tmp_path / "a.png").write_bytes(b"not a png")
    cv2.imwrite(str(tmp_path / "b.png"), np.full((4, 4), 7, np.uint8))
    src = FolderSource(tmp_path)
    assert src.read() is not None and src.unreadable == 1
    assert src.read() is None and src.ended
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="no images"):
        FolderSource(tmp_path / "empty")
