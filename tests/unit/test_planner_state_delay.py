"""How late a vehicle state reaches the planner (services/planner/state_delay.py): a backlog
after a stall is dropped, a constant clock offset between machines is not staleness, and the
tracker's state age is measured on one clock or above the lowest delay across machines.
"""
from __future__ import annotations

import pytest

from aeroperception.services.planner.state_delay import StateDelay

MS = 1_000_000
TIMEOUT_S = 0.5


def feed(d: StateDelay, now_ns: int, delay_ms: float) -> bool:
    return d.stale(now_ns, now_ns - round(delay_ms * MS), TIMEOUT_S)


def test_a_backlog_after_a_stall_is_dropped_and_counted():
    d = StateDelay()
    assert not feed(d, 10_000 * MS, 5)               # 5 ms: the usual latency
    assert feed(d, 11_000 * MS, 900)                 # delivered 0.9 s late after a stall
    assert d.stale_count == 1
    assert not feed(d, 11_020 * MS, 6)               # fresh again


def test_a_constant_clock_offset_between_machines_is_not_staleness():
    d = StateDelay()
    for i in range(20):                              # the other machine's clock is 3 s behind
        assert not feed(d, (10_000 + 20 * i) * MS, 3_000 + (i % 3))
    assert d.stale_count == 0


def test_the_lowest_delay_creeps_up_so_a_slower_link_is_followed():
    d = StateDelay()
    feed(d, 10_000 * MS, 5)
    for i in range(1, 101):                          # the link's latency settles 100 ms higher
        feed(d, (10_000 + 20 * i) * MS, 105)
    assert d.floor_ns == 105 * MS


def test_state_age_on_one_clock_is_the_delay_capped():
    d = StateDelay()
    feed(d, 10_000 * MS, 5)
    assert d.age_s(10_000 * MS, 9_980 * MS, TIMEOUT_S) == pytest.approx(0.020)
    assert d.age_s(10_000 * MS, 8_000 * MS, TIMEOUT_S) == TIMEOUT_S
    assert d.age_s(10_000 * MS, 10_010 * MS, TIMEOUT_S) == 0.0     # stamped ahead: not negative


def test_state_age_across_machines_is_the_delay_above_the_lowest():
    d = StateDelay()
    feed(d, 10_000 * MS, 3_000)                      # clock offset 3 s: not a latency
    assert d.age_s(10_020 * MS, (10_020 - 3_030) * MS, TIMEOUT_S) == pytest.approx(0.030)


def test_reset_forgets_the_other_sources_lowest_delay():
    d = StateDelay()
    feed(d, 10_000 * MS, 3_000)
    d.reset()
    assert not feed(d, 10_020 * MS, 5) and d.floor_ns == 5 * MS
