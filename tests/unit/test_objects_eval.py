"""`aero eval objects` scoring: found / missed / duplicated per class, false tracks and their
lifetime, position error at 5-30 m (and by range band), ID switches, time to confirmation, the
service's per-frame cost; which of the search flight's goals a result misses."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.schemas import TrackedObject, TrackedObjectArray, Vector3
from aeroperception.tools.eval.objects import ObjectsEval, Target, scenario_targets, table, unmet_goals

S = 1_000_000_000
TARGETS = [Target(0, "person", np.array([10.0, 0.0, 0.9])), Target(1, "person", np.array([20.0, 5.0, 0.9])),
           Target(2, "car", np.array([30.0, -5.0, 0.75]))]


def track(tid, cls, xyz, first_s=0.0, last_s=1.0, range_m=15.0, confirmed=True) -> TrackedObject:
    return TrackedObject(track_id=tid, class_name=cls, confirmed=confirmed, position_m=Vector3.from_array(xyz),
                         first_seen_ns=int(first_s * S), last_seen_ns=int(last_s * S), range_m=range_m)


def test_found_missed_duplicates_false_tracks_and_errors_per_class():
    ev = ObjectsEval(TARGETS)
    ev.add(TrackedObjectArray(objects=[
        track(1, "person", [10.3, 0.0, 0.9], 0.0, 0.4),                  # target 0, 0.3 m off
        track(2, "person", [10.0, 0.6, 0.9], 0.0, 0.5),                  # a second track on target 0
        track(3, "person", [40.0, 40.0, 0.9], 0.0, 3.0),                 # nothing there: false, lived 3 s
        track(4, "car", [30.0, -5.0, 0.75], range_m=40.0),               # beyond 30 m: found, no error sample
        track(5, "person", [20.0, 5.0, 0.9], confirmed=False),           # unconfirmed: not counted
    ]))
    r = ev.summary()
    p, c = r["classes"]["person"], r["classes"]["car"]
    assert (p["targets"], p["found"], p["missed"], p["duplicates"]) == (2, 1, 1, 1)
    assert (p["false_tracks"], p["false_tracks_over_2s"]) == (1, 1)
    assert p["error_samples"] == 2 and p["error_median_m"] == pytest.approx(0.45)
    assert (c["found"], c["missed"], c["error_samples"], c["error_median_m"]) == (1, 0, 0, None)
    assert r["confirm_s_median"] == pytest.approx(0.75) and r["confirm_s_max"] == pytest.approx(3.0)
    assert "person" in table(r) and "ID switches 0" in table(r)


def test_a_target_handed_to_another_track_is_an_id_switch():
    ev = ObjectsEval(TARGETS)
    ev.add(TrackedObjectArray(objects=[track(1, "person", [10.0, 0.0, 0.9])]))
    ev.add(TrackedObjectArray(objects=[track(1, "person", [10.1, 0.0, 0.9])]))
    ev.add(TrackedObjectArray(objects=[track(7, "person", [10.0, 0.1, 0.9])]))
    assert ev.summary()["id_switches"] == 1


def test_a_track_of_another_class_on_a_target_is_false():
    ev = ObjectsEval(TARGETS)
    ev.add(TrackedObjectArray(objects=[track(1, "truck", [30.0, -5.0, 0.75])]))
    r = ev.summary()
    assert r["classes"]["car"]["found"] == 0 and r["classes"]["truck"]["false_tracks"] == 1


def test_targets_come_from_the_scenario():
    t = scenario_targets("open_field")
    assert sorted(x.class_name for x in t) == ["car", "person", "person"]
    assert any(np.allclose(x.center_m[:2], [18, 1]) for x in t)


def test_errors_by_range_band_and_the_services_cost():
    ev = ObjectsEval(TARGETS)
    for k, (dx, rng) in enumerate([(0.1, 7.0), (0.2, 8.0), (0.4, 15.0), (1.0, 25.0), (2.0, 35.0)]):
        ev.add(TrackedObjectArray(objects=[track(1, "person", [10.0 + dx, 0.0, 0.9], range_m=rng)]))
    ev.add_diagnostics({"frame_cpu_ms_p50": "1.2", "frame_cpu_ms_p99": "3.1", "frame_cpu_ms_max": "7.0",
                        "frames_received": "40", "frames_processed": "38", "frames_dropped_busy": "2"})
    ev.add_diagnostics({"frame_cpu_ms_p50": "1.3", "frame_cpu_ms_p99": "3.3", "frame_cpu_ms_max": "4.0"})
    r = ev.summary()
    bands = r["classes"]["person"]["bands"]
    assert bands["5-10"] == {"median_m": pytest.approx(0.15), "p95_m": pytest.approx(0.195), "samples": 2}
    assert bands["10-20"]["samples"] == 1 and bands["20-30"]["median_m"] == pytest.approx(1.0)
    assert r["classes"]["person"]["error_samples"] == 4                  # 35 m: outside 5-30 m
    assert r["service"] == {"frame_cpu_ms_p50": 1.3, "frame_cpu_ms_p99": 3.3, "frame_cpu_ms_max": 7.0,
                            "frames_received": 40.0, "frames_processed": 38.0, "frames_dropped_busy": 2.0}
    assert "5-10 0.15/0.20 (2)" in table(r) and "2 dropped busy" in table(r)


def test_unmet_goals_name_each_miss():
    ev = ObjectsEval(TARGETS)
    ev.add(TrackedObjectArray(objects=[track(1, "person", [10.0, 0.0, 0.9]), track(2, "car", [30.0, -5.0, 0.75])]))
    ev.add_diagnostics({"frame_cpu_ms_p99": "1.0"})
    assert unmet_goals(ev.summary()) == ["person: 1 of 2 targets missed"]
    ev.add(TrackedObjectArray(objects=[
        track(1, "person", [10.0, 0.0, 0.9]), track(3, "person", [20.0, 6.9, 0.9]),
        track(4, "person", [10.5, 0.0, 0.9]), track(5, "car", [60.0, 0.0, 0.75], 0.0, 2.5)]))
    ev.add_diagnostics({"frame_cpu_ms_p99": "6.0"})
    assert unmet_goals(ev.summary()) == [
        "car: 1 false tracks living > 2 s ([2.5] s)", "person: 1 duplicate tracks",
        "person: position error p95 1.69 m (goal < 1.5 m)", "objects service: CPU p99 6.00 ms per frame (goal < 5 ms)"]
