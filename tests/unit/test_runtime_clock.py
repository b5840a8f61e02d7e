"""ServiceClock: wall time, or the sim clock followed (extrapolated, monotonic) when one is published."""
from __future__ import annotations

import time

import pytest

from aerotest import wait_until

from aeroperception.schemas import (
    Clock as ClockMsg, Header,
)
from aeroperception.services.runtime import (
    ServiceClock,
)


def test_clock_wall():
    c = ServiceClock()
    assert not c.is_sim
    assert abs(c.now_ns() - time.time_ns()) < 50_000_000


class _FakeNode:
    """Only what ServiceClock needs from a Node: subscribe()."""

    def __init__(self):
        self.subs = {}

    def subscribe(self, key, cls, cb):
        self.subs[key] = (cls, cb)


def test_clock_sim_follows_ticks_and_extrapolates_monotonic():
    node = _FakeNode()
    c = ServiceClock(node)
    assert c.is_sim and "sim/clock" in node.subs and node.subs["sim/clock"][0] is ClockMsg
    assert c.now_ns() == 0  # no tick heard: time has not started
    c._on_tick(ClockMsg(header=Header(stamp_ns=10_000_000_000), speed_factor=10.0))
    t1 = c.now_ns()
    assert 10_000_000_000 <= t1 < 10_500_000_000
    time.sleep(0.05)
    t2 = c.now_ns()
    assert t2 - t1 >= 0.4e9  # 50 ms wall at 10x is >= 0.4 s sim (allowing for timer slack)
    # A tick slightly behind the extrapolation does not make time go backwards.
    c._on_tick(ClockMsg(header=Header(stamp_ns=t2 - 1_000_000), speed_factor=10.0))
    assert c.now_ns() >= t2
    t0 = time.monotonic()
    c.sleep(0.5)  # half a sim second at 10x
    assert time.monotonic() - t0 < 0.3


@pytest.mark.timeout(30)
def test_clock_sim_through_a_real_node(make_node):
    follower = make_node("clockuser", sim_time=True)
    sim = make_node("fakesim")
    pub = sim.publisher("sim/clock", ClockMsg)
    assert follower.now_ns() == 0
    stamp = 123_000_000_000

    def ticked():
        pub.publish(ClockMsg(header=Header(stamp_ns=stamp), speed_factor=1.0))
        return follower.now_ns() >= stamp

    wait_until(ticked, 10, "the node to follow sim/clock")
    assert follower.now_ns() < stamp + 5_000_000_000
    assert follower.header().stamp_ns >= stamp
    wall = make_node("walluser")
    assert abs(wall.now_ns() - time.time_ns()) < 1e9
