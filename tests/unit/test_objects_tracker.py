"""Objects tracker: ByteTrack-style association and track life -- confirmed after N hits, lost
after T s unseen, low scores extend but never start tracks, one class per track, no ID switch
when two objects of different classes cross."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from aeroperception.services.objects.projection import Measurement
from aeroperception.services.objects import contract
from aeroperception.services.objects.tracker import Observation, Tracker, ObjectTrackerConfig
from aeroperception.services.runtime.config import build

MS = 1_000_000
PERSON, CAR = (0, "person"), (2, "car")


def obs(xy, cls=PERSON, score=0.9, sigma_m=0.3) -> Observation:
    m = Measurement(np.array([xy[0], xy[1], 0.9]), np.eye(3) * sigma_m ** 2, 15.0, "ground")
    return Observation(m, cls[0], cls[1], score)


def sighted(tr: Tracker, xy, box_scale: float, k: int):
    """Frame k (10 Hz) with one person at xy whose box is box_scale of a whole view's."""
    o = obs(xy, sigma_m=0.5)
    o.box_scale = box_scale
    return tr.update(k * 100 * MS, [o])


def test_a_track_is_confirmed_after_n_hits_and_lost_after_t_unseen():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, lost_timeout_s=1.0))
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
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, tentative_timeout_s=0.3))
    tr.update(0, [obs((10.0, 2.0))])
    ev = tr.expire(400 * MS)
    assert ev.lost == [] and ev.confirmed == [] and tr.tracks == []


def test_low_scores_extend_a_track_but_never_start_one():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, high_score=0.5, low_score=0.1))
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
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2))
    tr.update(0, [obs((10.0, 2.0))])
    tr.update(100 * MS, [obs((10.0, 2.0), CAR)])
    assert sorted((t.class_name, t.hits) for t in tr.tracks) == [("car", 1), ("person", 1)]


def test_a_far_detection_neither_captures_a_track_metres_away_nor_starts_one():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, gate_distance_m=3.0, birth_sigma_m=1.5))
    tr.update(0, [obs((10.0, 2.0))])
    tr.update(100 * MS, [obs((14.0, 2.0), sigma_m=5.0)])        # far: metres uncertain
    assert len(tr.tracks) == 1 and tr.tracks[0].hits == 1 and tr.tracks[0].x[0] == pytest.approx(10.0)
    tr.update(200 * MS, [obs((14.0, 2.0), sigma_m=0.3)])        # the same place, seen precisely: a second object
    assert sorted(t.x[0] for t in tr.tracks) == [10.0, 14.0]


def test_a_second_box_on_one_object_does_not_start_a_second_track():
    """The detector sometimes boxes one person twice (once taking in the car behind): the second
    placement, 1.8 m off but inside the track's Mahalanobis gate, is no second person."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3))
    for k in range(5):
        tr.update(k * 100 * MS, [obs((30.0, 4.0), sigma_m=0.5), obs((31.8, 4.2), score=0.6, sigma_m=0.8)])
    assert [(t.track_id, t.hits) for t in tr.tracks] == [(1, 5)]
    assert tr.tracks[0].x[0] == pytest.approx(30.0, abs=0.05)
    tr.update(600 * MS, [obs((36.0, 4.0), sigma_m=0.5)])        # well outside its gate: another person
    assert len(tr.tracks) == 2


def test_a_partial_box_keeps_a_track_alive_without_moving_it():
    """A box much shorter than the track's boxes (the object half hidden behind something nearer)
    has its centre off the object's: the track is seen (not lost) but stays where it was."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=1.0, partial_ratio=1.25))
    seen = functools.partial(sighted, tr)

    for k in range(4):
        seen((20.0, 2.0), 1.4, k)
    for k in range(4, 9):                                       # half-hidden boxes placed 0.8 m short
        assert seen((19.2, 2.0), 0.8, k).lost == []
    t = tr.tracks[0]
    assert t.hits == 9 and t.x[0] == pytest.approx(20.0, abs=0.05) and not t.x[3:].any()
    seen((20.1, 2.0), 1.3, 9)                                   # whole again: it moves
    assert t.x[0] > 20.0
    for k in range(10, 16):                                     # five partial views in a row, then
        seen((19.2, 2.0), 1.0, k)                               # the object looks different now: learnt anew
    assert t.x[0] < 19.9 and t.partial_run == 0


def test_a_run_of_boxes_smaller_than_its_class_is_never_learnt_as_its_new_look():
    """The detector boxing only a truck's cab, near and end-on, for many frames in a row: boxes
    shorter than its class's whole size (confirm_scale) placed 2.3 m short keep the track alive
    but never move it, however long the run; a whole view afterwards still does."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=1.0, partial_ratio=1.25, confirm_scale=0.92))
    seen = functools.partial(sighted, tr)
    for k in range(6):
        seen((72.0, 5.0), 1.3, k)
    t = tr.tracks[0]
    for k in range(6, 46):                                      # 4 s of cab-only boxes
        assert seen((69.7, 5.0), 0.8, k).lost == []
    assert t.last_seen_ns == 45 * 100 * MS and t.partial_run >= 39 and len(tr.tracks) == 1
    assert t.x[0] == pytest.approx(72.0, abs=0.05)
    seen((72.2, 5.0), 1.2, 46)
    assert t.x[0] > 72.0 and t.partial_run == 0


def test_a_box_shorter_than_the_tracks_whole_boxes_moves_it_by_less():
    """A box 0.8 of the track's whole boxes (the detector starting to box a truck's cab alone)
    may miss a fifth of the truck: its placement moves the track with 1 sigma 0.2 x 8 m = 1.6 m
    added horizontally; a box as tall as the track's, or with no class length, keeps its own."""
    def run(length_m: float, scale: float) -> float:
        tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, partial_ratio=1.3, partial_sigma_scale=1.0))
        for k in range(6):
            sighted(tr, (72.0, 5.0), 1.3, k)
        o = obs((70.0, 5.0), sigma_m=0.5)
        o.box_scale, o.length_m = scale, length_m
        tr.update(600 * MS, [o])
        return 72.0 - tr.tracks[0].x[0]

    unwidened, shrunk, whole = run(0.0, 1.04), run(8.0, 1.04), run(8.0, 1.3)
    assert whole == pytest.approx(unwidened) and unwidened > 0.5
    assert 0.0 < shrunk < 0.3 * unwidened
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, partial_sigma_scale=1.0))
    o = obs((70.0, 5.0), sigma_m=0.5)
    o.box_scale, o.length_m = 1.04, 8.0
    assert np.allclose(tr._widened(o, 1.3).covariance_m2, np.diag([0.25 + 1.6 ** 2, 0.25 + 1.6 ** 2, 0.25]))
    assert tr._widened(o, 0.0) is o.measurement and tr._widened(o, 1.0) is o.measurement


def test_ground_objects_do_not_climb_and_an_unseen_tracks_velocity_decays():
    """Placements that creep as the vehicle approaches (a range-dependent bias) must not read as a
    climb, and must not carry a static object away while it is unseen."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=5.0, coast_tau_s=0.5))
    for k in range(10):                                         # creeping 0.5 m/s east and 0.3 m/s up
        m = Measurement(np.array([10.0 + 0.05 * k, 2.0, 0.9 + 0.03 * k]), np.eye(3) * 0.01, 15.0, "stereo")
        tr.update(k * 100 * MS, [Observation(m, *PERSON, 0.9)])
    t = tr.tracks[0]
    assert t.x[5] == 0.0 and t.x[3] > 0.2
    x_seen = t.x[0]
    for k in range(10, 40):                                     # 3 s unseen
        tr.update(k * 100 * MS, [])
    assert t.x[0] - x_seen < 0.5 * t.x[3] + 0.35                # ~v * tau, not v * 3 s
    assert abs(t.x[3]) < 0.01


def test_a_lost_track_is_remembered_where_it_was_last_seen():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=1.0, coast_tau_s=0.0))
    for k in range(10):                                         # moving 1 m/s east, then unseen
        tr.update(k * 100 * MS, [obs((10.0 + 0.1 * k, 2.0), sigma_m=0.1)])
    last = tr.tracks[0].x[0]
    lost = tr.update(2200 * MS, []).lost
    assert len(lost) == 1 and lost[0].x[0] == pytest.approx(last) and not lost[0].x[3:].any()


def test_two_objects_of_different_classes_crossing_keep_their_ids():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3))
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
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3))
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
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=1.0, forget_s=60.0))
    for k in range(3):
        tr.update(k * 100 * MS, [obs((10.0, 2.0)), obs((30.0, 0.0), CAR)])
    assert [t.track_id for t in tr.update(1500 * MS, []).lost] == [1, 2]
    ev = tr.update(40_000 * MS, [obs((10.8, 2.3))])                   # the next leg, 40 s later
    assert [t.track_id for t in ev.reacquired] == [1] and ev.confirmed == []
    assert [t.track_id for t in tr.tracks] == [1] and tr.tracks[0].hits == 4
    assert tr.update(40_100 * MS, [obs((10.8, 2.3), CAR)]).reacquired == []   # another class: a new track
    assert tr.update(70_000 * MS, [obs((30.0, 0.0), CAR)]).reacquired == []   # car forgotten after 60 s
    assert 2 not in [t.track_id for t in tr.lost + tr.tracks]


def test_a_box_cut_by_the_images_edge_neither_moves_nor_starts_a_track():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2))
    for k in range(3):
        tr.update(k * 100 * MS, [obs((20.0, 2.0))])
    cut = obs((18.5, 2.0))
    cut.cut = True
    tr.update(300 * MS, [cut])
    t = tr.tracks[0]
    assert t.hits == 4 and t.x[0] == pytest.approx(20.0, abs=0.01)
    other = obs((40.0, 2.0))
    other.cut = True
    tr.update(400 * MS, [other])
    assert len(tr.tracks) == 1


@pytest.mark.parametrize("box_scale", [0.3, 2.4])
def test_a_box_implausible_for_its_class_neither_moves_nor_starts_a_track(box_scale):
    """Shorter than partial_scale of what the class fills from there (a car going under an awning,
    its boxes shrinking frame after frame), or taller than crowd_scale (a neighbour taken in):
    however many come in a row, they keep the track alive where its whole boxes put it."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, partial_scale=0.7, crowd_scale=2.0))
    seen = functools.partial(sighted, tr)

    for k in range(4):
        seen((20.0, 2.0), 1.2, k)
    for k in range(4, 14):                                      # ten in a row, 1.5 m short
        seen((18.5, 2.0), box_scale, k)
    t = tr.tracks[0]
    assert t.hits == 14 and t.x[0] == pytest.approx(20.0, abs=0.05)
    seen((40.0, 2.0), box_scale, 14)                            # nothing known there: starts nothing
    assert [x.track_id for x in tr.tracks] == [1]


TRUCK = (3, "truck")


def truck_seen(tr: Tracker, box_scale: float, k: int, cut: bool = False):
    """Frame k (10 Hz): one truck box at (80, -8), box_scale of its class's typical size."""
    o = obs((80.0, -8.0), TRUCK, score=0.55, sigma_m=0.5)
    o.box_scale, o.cut = box_scale, cut
    return tr.update(k * 100 * MS, [o])


def test_a_look_alike_smaller_than_its_class_is_held_tentative_however_long_it_is_seen():
    """A low wall (1.8 m, 10 m long) that the detector boxes as a 3.4 m truck fills 0.71-0.96 of
    a truck's box: seen 60 frames -- a late run of near-fitting views among them -- it is never
    confirmed, and it holds its place (no second track starts on it)."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, confirm_scale=0.92))
    scales = [0.78, 0.84, 0.80, 0.76, 0.83] * 8 + [0.94, 0.96, 0.93, 0.97, 0.95] * 3 + [0.75] * 5
    for k, s in enumerate(scales):
        assert truck_seen(tr, s, k).confirmed == []
    assert len(tr.tracks) == 1 and not tr.tracks[0].confirmed and tr.tracks[0].hits == 60


@pytest.mark.parametrize("scales", [[1.25, 1.2, 1.38], [0.95, 0.88, 1.1], [0.85, 0.8, 1.0, 1.05]])
def test_an_object_its_classs_size_is_confirmed_once_half_its_boxes_fit(scales):
    """Boxed at 1.10-1.31x its class's typical size (the detector's margin, median), a real object is
    confirmed at confirm_hits; a few short boxes among the first only wait until half fit."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, confirm_scale=0.92))
    confirmed = [k for k, s in enumerate(scales) if truck_seen(tr, s, k).confirmed]
    assert confirmed == [len(scales) - 1]


def test_boxes_cut_by_the_images_edge_never_count_against_the_class_size():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, confirm_scale=0.92))
    truck_seen(tr, 1.2, 0)
    truck_seen(tr, 0.4, 1, cut=True)                             # half the truck outside the image
    assert truck_seen(tr, 0.45, 2, cut=True).confirmed == tr.tracks


def test_confirm_scale_zero_confirms_any_size():
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=3, confirm_scale=0.0))
    assert [k for k in range(3) if truck_seen(tr, 0.8, k).confirmed] == [2]


def test_a_far_imprecise_placement_keeps_a_track_alive_without_dragging_it():
    """A track placed from near must not be pulled metres away by far placements (each a few
    metres biased, each inside the gate of where the last one left the track)."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, birth_sigma_m=2.0, lost_timeout_s=1.0))
    for k in range(5):
        tr.update(k * 100 * MS, [obs((20.0, 2.0), sigma_m=0.3)])
    for k in range(5, 15):                                      # 0.25 m further west each frame, sigma 2.3 m
        tr.update(k * 100 * MS, [obs((20.0 - 0.25 * (k - 4), 2.0), sigma_m=2.3)])
    t = tr.tracks[0]
    assert t.hits == 15 and t.x[0] == pytest.approx(20.0, abs=0.05) and tr.update(1500 * MS, []).lost == []


def test_a_biased_view_of_a_well_placed_object_is_no_second_object():
    """Seen many times from near, a person is placed to 0.1 m; a later view placed 2 m off with a
    covariance of 0.5 m (outside the Mahalanobis gate: the bias is not in the covariance) starts
    no second track while it lies within birth_spacing_m; beyond it, it does."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, birth_spacing_m=2.5))
    for k in range(30):
        tr.update(k * 100 * MS, [obs((20.0, 2.0), sigma_m=0.3)])
    for k in range(30, 35):
        tr.update(k * 100 * MS, [obs((20.0, 2.0), sigma_m=0.3), obs((22.0, 2.4), sigma_m=0.5)])
    assert [t.track_id for t in tr.tracks] == [1]
    tr.update(3500 * MS, [obs((20.0, 2.0), sigma_m=0.3), obs((23.0, 2.0), sigma_m=0.5)])
    assert len(tr.tracks) == 2


def test_a_far_view_within_three_of_its_sigmas_of_a_known_object_is_that_object():
    """From 35 m a person's box (taking in the car in front) is placed 5 m off its track: within 3
    sigma (1.9 m) of the placement, so no second person; seen from near, a person there is."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, birth_spacing_m=2.5, birth_sigma_m=2.0))
    for k in range(10):
        tr.update(k * 100 * MS, [obs((12.0, -5.0), sigma_m=0.3)])
    for k in range(10, 15):
        tr.update(k * 100 * MS, [obs((17.0, -4.3), sigma_m=1.9)])
    assert [t.track_id for t in tr.tracks] == [1]
    tr.update(1500 * MS, [obs((17.0, -4.3), sigma_m=0.4)])
    assert len(tr.tracks) == 2


def test_a_coasting_tracks_velocity_uncertainty_decays_with_its_velocity():
    """Kept alive for seconds by views that do not move it, a track must not come out of it so
    loose that its next whole view (biased by a metre near) throws it past where the object is."""
    tr = Tracker(build(ObjectTrackerConfig, contract.PARAMS, confirm_hits=2, lost_timeout_s=10.0, coast_tau_s=0.5))
    for k in range(10):
        tr.update(k * 100 * MS, [obs((20.0, 2.0), sigma_m=0.3)])
    for k in range(10, 50):                                     # 4 s of cut boxes: alive, unmoved
        cut = obs((20.0, 2.0))
        cut.cut = True
        tr.update(k * 100 * MS, [cut])
    t = tr.tracks[0]
    assert t.P[3, 3] < 0.01 and t.P[0, 0] < 0.2
    tr.update(5000 * MS, [obs((19.0, 2.0), sigma_m=0.3)])         # a whole view 1 m off
    assert 19.0 < t.x[0] < 20.0
