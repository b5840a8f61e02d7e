"""`aero bench pubsub --peers` (tools/bench/pubsub.py): every transport it compares carries the
same payload both ways. Latency figures are not asserted (the machine is shared); that each path
delivers every round trip, with a one-way time that is plausible, is."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from aerotest import free_port

from aeroperception.tools.bench import pubsub as bench

N = 30


def _check(lat: np.ndarray) -> None:
    assert len(lat) == N, f"{N - len(lat)} round trips lost"
    assert 0.0 < np.median(lat) < 50.0, np.median(lat)


@pytest.mark.parametrize("path", ["raw", "read", "typed"])
@pytest.mark.parametrize("kind", ["state", "image"])
def test_zenoh_peer_to_peer_without_a_router(path, kind):
    _check(bench.measure(f"tcp/127.0.0.1:{free_port()}", path, kind, N, "peer"))


@pytest.mark.parametrize("path", ["raw", "typed"])
def test_zenoh_peers_introduced_by_the_router(zenoh_router, path):
    _check(bench.measure(zenoh_router, path, "state", N, "mesh"))


@pytest.mark.skipif(not importlib.util.find_spec("cyclonedds"), reason="extra `bench` (cyclonedds) not installed")
def test_cyclone_dds_ping_pong():
    _check(bench.measure_dds("state", N))


@pytest.mark.skipif(bool(bench.peers_available()["dora-rs"]), reason="extra `bench` (dora-rs) not installed")
def test_dora_two_node_dataflow_ping_pong():
    _check(bench.measure_dora("state", N, timeout_s=60.0))
