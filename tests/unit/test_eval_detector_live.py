"""The pure parts of `aero eval detector --live` (tools/eval/detector.py): stamp pairing, the
one-flight watch behind --until-landed, and the window's rates and detector counter deltas."""
import pytest

from aeroperception.tools.common import FlightWatch
from aeroperception.tools.eval.detector import LiveWindow, StampPairer


def test_pairs_by_equal_stamp_in_either_order_and_bounds_the_unmatched():
    p = StampPairer(keep=3)
    assert p.add(0, 10, "img10") is None
    assert p.add(1, 10, "tru10") == ("img10", "tru10")
    assert p.add(1, 20, "tru20") is None
    assert p.add(0, 20, "img20") == ("img20", "tru20")        # (side 0, side 1) whatever came first
    assert p.add(0, 30, "img30") is None and p.add(1, 31, "tru31") is None   # different stamps never pair
    for s in range(40, 45):
        p.add(0, s, f"img{s}")
    assert list(p.sides[0]) == [42, 43, 44]                   # newest `keep` kept
    assert p.add(1, 30, "tru30") is None                      # img30 was evicted


def test_flight_watch_needs_a_flight_before_landed():
    w = FlightWatch()
    w.update(False, 0.0)
    w.update(True, 0.3)                                       # armed on the ground: not flown yet
    assert not w.flew.is_set() and not w.down.is_set()
    w.update(True, 3.0)
    w.update(True, 0.1)                                       # touched down, still armed
    assert w.flew.is_set() and not w.down.is_set()
    w.update(False, 0.05)
    assert w.down.is_set()


def test_window_rates_and_detector_counter_deltas():
    w = LiveWindow(seconds=10.0, camera=30, truth=30, detections=28, pairs=25)
    assert w.rates() == pytest.approx({"camera_hz": 3.0, "truth_hz": 3.0, "detections_hz": 2.8, "evaluated_hz": 2.5})
    assert w.detector_counts() == {}
    w.health = [{"frames_received": 100, "frames_processed": 99, "frames_skipped_rate": 0, "frames_dropped_busy": 1},
                {"frames_received": 130, "frames_processed": 128, "frames_skipped_rate": 0, "frames_dropped_busy": 2}]
    assert w.detector_counts() == {"frames_received": 30, "frames_processed": 29, "frames_skipped_rate": 0,
                                   "frames_dropped_busy": 1}
