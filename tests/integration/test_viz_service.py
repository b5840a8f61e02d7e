"""The viz service on a real (in-process) Zenoh router, no stack: when the viewer it streams to is
absent it drops new data (counted in its diagnostics) instead of letting Rerun buffer, its
callbacks stay cheap, it samples to its rates, and it still stops within the 2 s budget."""
from __future__ import annotations

import argparse
import socket
import time

from aerotest import wait_until
from aeroperception.schemas import Header, Vector3, VehicleState
from aeroperception.services.viz import contract
from aeroperception.services.viz.main import VizService


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]          # closed again when this returns: nobody listens


def test_absent_viewer_means_counted_drops_not_a_queue_and_a_prompt_stop(make_node, tmp_path):
    node = make_node("viz", params=contract.PARAMS)
    node.params.update({"web_port": 0, "viewer_url": f"rerun+http://127.0.0.1:{closed_port()}/proxy",
                        "save_path": str(tmp_path / "v.rrd"), "flush_timeout_s": 0.2, "pose_rate_hz": 10.0})
    svc = VizService(node, argparse.Namespace())
    with node.lock:
        svc.start()
    pub_node = make_node("test-fmu")
    pub = pub_node.publisher("state/vehicle", VehicleState)
    try:
        t0 = time.monotonic()
        sent = 0
        while time.monotonic() - t0 < 4.0:                   # 50 Hz for 4 s
            pub.publish(VehicleState(header=Header(stamp_ns=time.time_ns(), frame_id="map"),
                                     position_m=Vector3(x=0.01 * sent), connected=True))
            sent += 1
            time.sleep(0.02)
        wait_until(lambda: svc.received["state/vehicle"] >= 0.8 * sent, 3, "viz received the states")
        h = svc.health()
        v = h.values
        assert svc.sink.backlogged and h.message.startswith("viewer behind"), (h.message, v)
        assert v["dropped_viewer_behind"] > 0, v
        assert v["viewer_behind_episodes"] >= 1, v
        assert v["sampled_out"] > 0.5 * sent, v               # 10 of 50 Hz kept
        assert v["logged"] <= 0.3 * sent, v                   # nothing piled up behind the sampler
    finally:
        t = time.monotonic()
        svc.stop()
        stop_s = time.monotonic() - t
    assert stop_s < 2.0, f"stop took {stop_s:.2f} s with an absent viewer"
