"""Objects tracker: ByteTrack-style association and track life -- confirmed after N hits, lost
after T s unseen, low scores extend but never start tracks, one class per track, no ID switch
when two objects of different classes cross."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.services.objects.projection import Measurement
from aeroperception.services.objects.tracker import Observation, Tracker, TrackerConfig

MS = 1_000_000
PERSON, CAR = (0, "person"), (2, "car")


def obs(xy, cls=PERSON, score=0.9, sigma_m=0.3) -> Observation:
    m = Measurement(np.array([xy[0], xy[1], 0.9]), np.eye(3) * sigma_m ** 2, 15.0, "ground")
    return Observation(m, cls[0], cls[1], score)


def test_a_track_is_confirmed_after_n_hits_and_lost_after_t_unseen():
    tr = Tracker(TrackerConfig(confirm_hits=3, lost_timeout_s=1.0))
    confirmed_at = None
    for k in range(5):
        ev = tr.update(k * 100 * MS, [obs((10.0, 2.0))])
        if ev.confirmed:
            confirmed_at = k
            assert [t.track_id for t in ev.confirmed] == [1]
    assert confirmed_at == 2 and len(tr.tracks) == 1 and tr.tracks[0].hits == 5
    assert tr.update(1300 * MS, []).lost == []                  # 0.9 s unseen
    lost = tr.update(1500 * MS, []).lost                        # 1.1 s unseen
    assert [t.track_id for t in lost] == [1] and tr.tracks == []


def test_an_unconfirmed_track_is_dropped_without_an_event():
    tr = Tracker(TrackerConfig(confirm_hits=3, tentative_timeout_s=0.3))
    tr.update(0, [obs((10.0, 2.0))])
    ev = tr.expire(400 * MS)
    assert ev.lost == [] and ev.confirmed == [] and tr.tracks == []


def test_low_scores_extend_a_track_but_never_start_one():
    tr = Tracker(TrackerConfig(confirm_hits=3, high_score=0.5, low_score=0.1))
    tr.update(0, [obs((10.0, 2.0), score=0.3)])
    assert tr.tracks == []
    tr.update(100 * MS, [obs((10.0, 2.0), score=0.8)])
    ev1 = tr.update(200 * MS, [obs((10.1, 2.0), score=0.3)])
    ev2 = tr.update(300 * MS, [obs((10.0, 2.1), score=0.2)])
    assert len(tr.tracks) == 1 and tr.tracks[0].hits == 3 and ev1.confirmed == [] and len(ev2.confirmed) == 1
    assert tr.tracks[0].best_score == pytest.approx(0.8)
    tr.update(400 * MS, [obs((10.0, 2.0), score=0.05)])         # below low_score: ignored
    assert tr.tracks[0].hits == 3


def test_a_detection_of_another_class_never_joins_a_track():
    tr = Tracker(TrackerConfig(confirm_hits=2))
    tr.update(0, [obs((10.0, 2.0))])
    tr.update(100 * MS, [obs((10.0, 2.0), CAR)])
    assert sorted((t.class_name, t.hits) for t in tr.tracks) == [("car", 1), ("person", 1)]


def test_far_detections_start_their_own_track_despite_wide_covariances():
    tr = Tracker(TrackerConfig(gate_distance_m=3.0))
    tr.update(0, [obs((10.0, 2.0), sigma_m=5.0)])
    tr.update(100 * MS, [obs((14.0, 2.0), sigma_m=5.0)])
    assert len(tr.tracks) == 2


def test_two_objects_of_different_classes_crossing_keep_their_ids():
    tr = Tracker(TrackerConfig(confirm_hits=3))
    ids: dict[str, set[int]] = {"person": set(), "car": set()}
    rng = np.random.default_rng(0)
    for k in range(40):                                         # 10 Hz, 4 s; they meet at k = 20
        t = k * 0.1
        person = (10.0 + 1.0 * t, 0.0)                          # east at 1 m/s
        car = (14.0 - 1.0 * t, 0.2)                             # west at 1 m/s
        tr.update(k * 100 * MS, [obs(np.add(person, rng.normal(0, 0.1, 2))),
                                 obs(np.add(car, rng.normal(0, 0.1, 2)), CAR)])
        for tk in tr.tracks:
            ids[tk.class_name].add(tk.track_id)
    assert ids == {"person": {1}, "car": {2}}
    p = next(t for t in tr.tracks if t.class_name == "person")
    c = next(t for t in tr.tracks if t.class_name == "car")
    assert p.x[3] == pytest.approx(1.0, abs=0.3) and c.x[3] == pytest.approx(-1.0, abs=0.3)


def test_two_people_crossing_keep_their_ids_by_their_velocity():
    tr = Tracker(TrackerConfig(confirm_hits=3))
    seen: dict[int, list[float]] = {}
    for k in range(40):
        t = k * 0.1
        a, b = (10.0 + 1.0 * t, 1.0 - 0.05 * t), (14.0 - 1.0 * t, -1.0 + 0.05 * t)   # cross at k = 20
        tr.update(k * 100 * MS, [obs(a, sigma_m=0.1), obs(b, sigma_m=0.1)])
        for tk in tr.tracks:
            seen.setdefault(tk.track_id, []).append(float(tk.x[0]))
    assert sorted(seen) == [1, 2]
    assert seen[1][-1] > 13.0 and seen[2][-1] < 11.0            # each went on the way it came


def test_a_lost_object_seen_again_is_reacquired_under_its_id_until_forgotten():
    tr = Tracker(TrackerConfig(confirm_hits=2, lost_timeout_s=1.0, forget_s=60.0))
    for k in range(3):
        tr.update(k * 100 * MS, [obs((10.0, 2.0)), obs((30.0, 0.0), CAR)])
    assert [t.track_id for t in tr.update(1500 * MS, []).lost] == [1, 2]
    ev = tr.update(40_000 * MS, [obs((10.8, 2.3))])                   # the next leg, 40 s later
    assert [t.track_id for t in ev.reacquired] == [1] and ev.confirmed == []
    assert [t.track_id for t in tr.tracks] == [1] and tr.tracks[0].hits == 4
    assert tr.update(40_100 * MS, [obs((10.8, 2.3), CAR)]).reacquired == []   # another class: a new track
    assert tr.update(70_000 * MS, [obs((30.0, 0.0), CAR)]).reacquired == []   # car forgotten after 60 s
    assert 2 not in [t.track_id for t in tr.lost + tr.tracks]
