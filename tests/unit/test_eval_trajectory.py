"""`aero eval trajectory`'s figures from known motions."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.tools.eval.trajectory import TrajectoryEval, distances_to_polyline

SQUARE = np.array([[0, 0, 5], [10, 0, 5], [10, 10, 5]], float)


def flown(ev: TrajectoryEval, positions: np.ndarray, dt: float = 0.02) -> None:
    vel = np.gradient(positions, dt, axis=0)
    for k, (p, v) in enumerate(zip(positions, vel)):
        ev.add_truth(k * dt, p, v)


def test_on_the_legs_at_constant_speed_scores_zero_cross_track_and_no_acceleration():
    s = np.linspace(0, 20, 1001)                       # 20 m at 1 m/s along the two legs
    pos = np.array([[min(d, 10), max(0, d - 10), 5] for d in s])
    ev = TrajectoryEval(SQUARE)
    flown(ev, pos)
    ev.add_reached(0, 0.0)
    ev.add_reached(2, 20.0)
    res = ev.summary()
    assert res["time_s"] == 20.0 and res["cross_track_max_m"] < 1e-9
    assert res["peak_xy_speed_mps"] == pytest.approx(1.0, abs=0.01)
    assert res["corner_overshoot_m"] == [0.0] and res["reference_error_rms_m"] is None


def test_overshoot_is_the_outside_of_the_turn_and_cross_track_is_by_distance():
    # along x to 10.4 (0.4 m past the left turn at (10, 0): outside), then up the second leg
    pos = np.vstack([np.column_stack([np.linspace(0, 10.4, 500), np.zeros(500), np.full(500, 5.0)]),
                     np.column_stack([np.full(500, 10.4), np.linspace(0, 10, 500), np.full(500, 5.0)])])
    ev = TrajectoryEval(SQUARE)
    flown(ev, pos)
    ev.add_reached(0, 0.0)
    ev.add_reached(2, 1000 * 0.02)
    res = ev.summary()
    assert res["corner_overshoot_m"][0] == pytest.approx(0.4, abs=1e-6)
    assert res["cross_track_max_m"] == pytest.approx(0.4, abs=1e-6)
    high = TrajectoryEval(SQUARE)                  # 0.6 m above the legs throughout (an estimate's height offset)
    flown(high, pos + [0, 0, 0.6])
    high.add_reached(0, 0.0)
    high.add_reached(2, 1000 * 0.02)
    assert high.summary()["corner_overshoot_m"][0] == pytest.approx(0.4, abs=1e-6)   # a swing is horizontal


def test_peaks_of_a_constant_acceleration_and_an_incomplete_flight_is_refused():
    t = np.arange(0, 4.0, 0.02)
    pos = np.column_stack([0.5 * 1.5 * t ** 2, np.zeros_like(t), np.full_like(t, 5.0)])   # 1.5 m/s^2 along x
    ev = TrajectoryEval(np.array([[0, 0, 5], [20, 0, 5]], float))
    flown(ev, pos)
    ev.add_reached(0, 0.0)
    with pytest.raises(ValueError, match=r"\[1\] never reached"):
        ev.summary()
    ev.add_reached(1, t[-1])
    res = ev.summary()
    assert res["peak_xy_acc_mps2"] == pytest.approx(1.5, abs=0.05) and res["peak_jerk_mps3"] < 0.5


def test_distance_to_a_polyline():
    d = distances_to_polyline(np.array([[5, 1, 5], [12, 5, 5], [-1, 0, 5]], float), SQUARE)
    assert d == pytest.approx([1.0, 2.0, 1.0])


def test_horizontal_cross_track_leaves_out_a_height_offset():
    """A flight controller's height estimate 0.5 m off the truth: on the legs horizontally."""
    pos = np.column_stack([np.linspace(0, 10, 500), np.full(500, 0.1), np.full(500, 5.5)])
    ev = TrajectoryEval(np.array([[0, 0, 5], [10, 0, 5]], float))
    flown(ev, pos)
    ev.add_reached(0, 0.0)
    ev.add_reached(1, 499 * 0.02)
    res = ev.summary()
    assert res["cross_track_rms_m"] == pytest.approx(math.hypot(0.1, 0.5), abs=1e-3)
    assert res["cross_track_xy_rms_m"] == pytest.approx(0.1, abs=1e-6) and res["cross_track_xy_max_m"] == pytest.approx(0.1, abs=1e-6)


def test_jerk_is_scored_in_3d_and_horizontally_apart():
    """A height hold's bob (no vertical motion asked) counts in the 3-D jerk, not in the horizontal
    one: 0.05 m at 1 Hz has a jerk of 0.05 (2 pi)^3 = 12.4 m/s^3."""
    t = np.arange(0, 10.0, 0.01)
    pos = np.column_stack([t, np.zeros_like(t), 5.0 + 0.05 * np.sin(2 * math.pi * t)])   # 1 m/s along x
    ev = TrajectoryEval(np.array([[0, 0, 5], [10, 0, 5]], float))
    flown(ev, pos, dt=0.01)
    ev.add_reached(0, 0.0)
    ev.add_reached(1, t[-1])
    res = ev.summary()
    assert res["peak_xy_jerk_mps3"] < 0.1
    assert 9.0 < res["peak_jerk_mps3"] < 12.5          # the eval's 0.2 s differences round the peak off a little
