"""The physics thread hands frames to the render processes through a pipe: that hand-off must
never block, also while a renderer is still starting (at load 20 a child took 25 s to start, the
pipe filled in ~8 s and the vehicle's MAVLink stopped mid-boot)."""
from __future__ import annotations

import time

import numpy as np

from aeroperception.services.sim.render import RenderProcess
from aeroperception.services.sim.sensors.synthetic import hover_truth
from aeroperception.tools.harness import free_port


def test_requests_to_a_renderer_that_is_not_ready_are_skipped_not_queued():
    # No router on this port: the child waits for one and never becomes ready.
    w = RenderProcess("camera", "open_field", {"connect": f"tcp/127.0.0.1:{free_port()}"})
    try:
        truth = hover_truth(np.array([0.0, 0.0, 3.0]))
        t0 = time.monotonic()
        for i in range(3000):      # ~3 MB of pickles: would fill the pipe many times over
            w.request(truth, i)
        assert time.monotonic() - t0 < 2.0
        assert (w.requested, w.skipped, w.ready) == (3000, 3000, False)
    finally:
        w.stop(timeout_s=0.5)
