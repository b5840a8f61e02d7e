"""Zenoh QoS of the simulator's streams, by key (one home for main.py and the render processes).

The small high-rate streams must not be lost behind the ~1 MB images and scans on the same link:
with zenoh's defaults (priority DATA, congestion control DROP) 5-10 % of IMU / clock / truth
samples were dropped, in bursts of up to ~90 ms, while frames were in flight. A higher priority
gives them their own queue ahead of the frames; BLOCK makes them wait instead of vanishing.
Images and scans keep DROP (a late frame is better skipped than queued) at priority DATA_LOW: on
a slow link to another host (radio, 20 Mbit/s) they yield to state, goals and service replies;
at DATA, 20 Hz raw frames starved a ground station's arm request until it timed out
(tests/integration/test_multihost.py::test_impaired_link).
"""
from __future__ import annotations

import zenoh

SMALL_STREAMS = ("sensors/imu", "sim/clock", "sim/truth/state")
BULK_STREAMS = ("sensors/camera/left/image", "sensors/camera/right/image", "sensors/lidar/points",
                "sim/truth/lidar_labels")


def qos_for(key: str) -> dict:
    """Keyword arguments for Node.publisher(key, ...)."""
    if key in SMALL_STREAMS:
        return dict(express=True, priority=zenoh.Priority.DATA_HIGH, congestion_control=zenoh.CongestionControl.BLOCK)
    if key in BULK_STREAMS:
        return dict(priority=zenoh.Priority.DATA_LOW, congestion_control=zenoh.CongestionControl.DROP)
    return {}
