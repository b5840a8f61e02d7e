"""RateLoop: the period kept by deadline, overruns counted without bursts, exceptions survived, fast stop."""
from __future__ import annotations

import threading
import time

import pytest

from aerotest import wait_until

from aeroperception.services.runtime import (
    RateLoop,
)


@pytest.mark.timeout(30)
def test_rate_loop_keeps_period_by_deadline_with_heavy_body():
    """A body taking 60% of the period: a sleep(period) loop would run at 1.6x the period;
    a deadline loop keeps the mean period."""
    period = 0.025
    stamps: list[float] = []

    def body():
        stamps.append(time.perf_counter())
        time.sleep(0.6 * period)

    loop = RateLoop(1 / period, body, name="t").start()
    time.sleep(1.5)
    loop.stop()
    assert len(stamps) > 20
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    mean = sum(gaps) / len(gaps)
    assert 0.9 * period < mean < 1.2 * period, f"mean period {mean * 1e3:.1f} ms, want {period * 1e3:.0f} ms"
    s = loop.stats.summary()
    assert s["ticks"] == len(stamps)
    assert {"period_error_p50_ms", "period_error_p99_ms", "work_p50_ms", "work_p99_ms"} <= set(s)
    assert s["work_p50_ms"] >= 0.5 * 0.6 * period * 1e3
    # Jitter is reported: the median period error is small against the period.
    assert s["period_error_p50_ms"] < 0.5 * period * 1e3


@pytest.mark.timeout(30)
def test_rate_loop_counts_overruns_and_does_not_burst():
    period = 0.02
    stamps: list[float] = []
    slow = threading.Event()
    slow.set()

    def body():
        stamps.append(time.perf_counter())
        if slow.is_set() and len(stamps) <= 5:
            time.sleep(3 * period)  # falls more than one period behind

    loop = RateLoop(1 / period, body).start()
    wait_until(lambda: len(stamps) >= 15, 10, "15 ticks")
    loop.stop()
    assert loop.stats.overruns >= 1
    # After the slow ticks the loop skips ahead instead of firing a burst of catch-up ticks.
    gaps = [b - a for a, b in zip(stamps[4:], stamps[5:])]
    assert min(gaps) > 0.5 * period, f"burst after overrun: gaps {[round(g * 1e3, 1) for g in gaps]} ms"


def test_rate_loop_survives_exceptions_and_stops_fast():
    errors: list[BaseException] = []
    n = [0]

    def body():
        n[0] += 1
        raise RuntimeError("boom")

    loop = RateLoop(100, body, on_error=errors.append).start()
    wait_until(lambda: n[0] >= 5, 5, "5 ticks")
    t0 = time.monotonic()
    loop.stop()
    assert time.monotonic() - t0 < 0.5
    assert len(errors) >= 5 and all(isinstance(e, RuntimeError) for e in errors)
    count = n[0]
    time.sleep(0.05)
    assert n[0] == count  # really stopped


def test_rate_loop_stop_interrupts_long_wait_and_set_rate():
    loop = RateLoop(0.2, lambda: None).start()  # 5 s period
    time.sleep(0.05)
    t0 = time.monotonic()
    loop.stop()
    assert time.monotonic() - t0 < 0.5
    loop.set_rate(50)
    assert loop.period_s == pytest.approx(0.02)
    with pytest.raises(ValueError):
        RateLoop(0, lambda: None)
