"""The runtime's input thinning (services/runtime/latest.py): RateGate never passes more than its
rate on average and passes a source at exactly its rate whole despite jitter (the detector gates
camera frames by arrival, the lidar service scans by their stamps)."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.services.runtime import RateGate


@pytest.mark.parametrize("camera_hz,rate_hz", [(20.0, 10.0), (10.0, 10.0), (12.0, 10.0), (30.0, 7.0), (5.0, 10.0)])
def test_rate_gate_never_exceeds_the_rate(camera_hz, rate_hz):
    rng = np.random.default_rng(1)
    gate = RateGate(rate_hz)
    t = np.arange(0, 20.0, 1 / camera_hz) + rng.uniform(-0.1, 0.1, int(20.0 * camera_hz)) / camera_hz   # 10 % jitter
    admitted = np.array([s for s in t if gate.admit(s)])
    for start in np.arange(0, 19.0, 0.5):                     # every 1 s window
        n = np.count_nonzero((admitted >= start) & (admitted < start + 1.0))
        assert n <= rate_hz + 2            # the bucket's depth, after the start
    expected = min(camera_hz, rate_hz)
    assert len(admitted) / 20.0 == pytest.approx(expected, rel=0.12)
    assert gate.admitted + gate.skipped == len(t)


def test_rate_gate_by_stamps_passes_a_sensor_at_the_rate_whole_and_survives_a_restart():
    gate = RateGate(10.0)
    stamps = [i * 0.1 for i in range(50)]                  # a 10 Hz LiDAR's stamps
    assert all(gate.admit(s) for s in stamps)
    assert not gate.admit(stamps[-1])                      # the same scan again: thinned
    restarted = [100.0 + i * 0.1 for i in range(10)]       # ...and a sim whose clock restarted lower
    assert sum(gate.admit(s - 200.0) for s in restarted) >= 9


def test_rate_gate_passes_a_source_at_its_rate_whole_despite_30_percent_jitter():
    rng = np.random.default_rng(7)
    gate = RateGate(10.0)
    arrivals = np.arange(200) * 0.1 + rng.uniform(-0.03, 0.03, 200)
    assert all(gate.admit(t) for t in arrivals)
