"""The simulator's camera streams follow contract.OUTPUTS: every camera the rig builds is rendered
and published on sensors/camera/<name>/image only while someone subscribes, a camera slower than
the frame requests (the down camera) at its own rate, and a camera the contract lacks is refused."""
from __future__ import annotations

import types

import numpy as np
import pytest

from aeroperception.services.sim import contract
from aeroperception.services.sim.qos import BULK_STREAMS
from aeroperception.services.sim.render import _CameraRenderer


class FakeCamera:
    def __init__(self, name: str, rate_hz: float):
        self.frame_id, self.rate_hz, self.width, self.height = f"camera_{name}_optical", rate_hz, 8, 6
        self.rendered = 0

    def render(self, _truth):
        self.rendered += 1
        return np.zeros((self.height, self.width), np.uint8)


class FakePub:
    def __init__(self):
        self.matched, self.sent = False, []

    def publish(self, msg):
        self.sent.append(msg)


def rig(**cams):
    return types.SimpleNamespace(stereo=None, cameras=lambda: cams)


def test_every_declared_camera_is_a_bulk_stream_with_its_info():
    assert contract.CAMERAS == ("left", "right", "down")
    for name in contract.CAMERAS:
        assert f"sensors/camera/{name}/image" in BULK_STREAMS
        assert f"sensors/camera/{name}/info" in contract.OUTPUTS and f"sensors/camera/{name}/info" in contract.SERVICES


def test_the_down_camera_is_rendered_only_while_subscribed_and_at_its_own_rate():
    left, down = FakeCamera("left", 20.0), FakeCamera("down", 10.0)
    io = {k: FakePub() for k in contract.RENDERED["camera"]}
    render = _CameraRenderer(io, rig(left=left, down=down), types.SimpleNamespace(targets=[]))
    warmup = down.rendered
    assert not render(None, 0)                                  # nobody subscribes: nothing rendered
    io["sensors/camera/down/image"].matched = True
    for k in range(10):                                         # 0.5 s of 20 Hz requests
        render(None, k * 50_000_000)
    assert len(io["sensors/camera/down/image"].sent) == 5 and down.rendered - warmup == 5
    assert not io["sensors/camera/left/image"].sent
    assert io["sensors/camera/down/image"].sent[0].header.frame_id == "camera_down_optical"


def test_a_camera_the_contract_does_not_declare_is_refused():
    io = {k: FakePub() for k in contract.RENDERED["camera"]}
    with pytest.raises(RuntimeError, match="camera rear is built but not declared"):
        _CameraRenderer(io, rig(rear=FakeCamera("rear", 10.0)), types.SimpleNamespace(targets=[]))
