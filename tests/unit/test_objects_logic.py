"""Objects pipeline (no Zenoh): a detection frame is placed at its image's pose (stereo when the
pair is there, else the ground ray), tracked, and given lat/lon about the FC's home; frames it
cannot place are counted by reason; one frame of ten boxes costs well under 5 ms."""
from __future__ import annotations

import numpy as np
import pytest

from test_objects_projection import FX, BASELINE, infos, project, textured_pair

from aeroperception.schemas import (
    Detection2D, Detection2DArray, Header, HomePosition, Image, ObjectEvent, Quaternion, Vector3, VehicleState,
)
from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.objects import contract
from aeroperception.services.objects.logic import ObjectsConfig, ObjectsPipeline
from aeroperception.services.objects.projection import PoseSample
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.rotations import quat_from_euler

MS = 1_000_000
T0 = 1_700_000_000_000_000_000
PITCH = 0.3
HOME = HomePosition(latitude_deg=47.397742, longitude_deg=8.545594, altitude_amsl_m=488.0,
                    position_m=Vector3(x=1.0, y=-2.0, z=0.0))


def pipeline(**overrides) -> ObjectsPipeline:
    pl = ObjectsPipeline(build(ObjectsConfig, {**{p.name: p.default for p in contract.PARAMS}, **overrides}))
    left, right = infos(PITCH)
    pl.on_info("left", left)
    pl.on_info("right", right)
    pl.on_home(HOME)
    return pl


def feed_states(pl, until_ns, position=(0.0, 0.0, 10.0)):
    for t in range(T0 - 500 * MS, until_ns + 40 * MS, 20 * MS):
        pl.on_state(VehicleState(header=Header(stamp_ns=t), position_m=Vector3.from_array(position),
                                 orientation=Quaternion.from_array(quat_from_euler(0.0, 0.0, 0.0))))


def frame(stamp_ns, boxes) -> Detection2DArray:
    return Detection2DArray(header=Header(stamp_ns=stamp_ns, frame_id="camera_left_optical"), image_width=640,
                            image_height=480, detections=[Detection2D(center_x_px=u, center_y_px=v, size_x_px=w,
                                                                      size_y_px=h, class_id=0, class_name="person",
                                                                      score=0.9) for u, v, w, h in boxes])


def person_box(truth, position=(0.0, 0.0, 10.0), pitch_rad=0.0):
    """The box of a person at `truth` seen from `position`, the vehicle pitched nose down `pitch_rad`."""
    pose = PoseSample(0, np.asarray(position, float), quat_from_euler(0.0, pitch_rad, 0.0))
    u, v, z = project(truth, pose, PITCH)
    return u, v, FX * 0.5 / z, FX * 1.75 / z


def test_a_person_becomes_a_confirmed_track_at_its_position_with_lat_lon_about_home():
    pl = pipeline(stereo=False, confirm_hits=3)
    truth = np.array([20.0, 3.0, 0.875])
    feed_states(pl, T0 + 400 * MS)
    events = []
    for k in range(4):
        r = pl.process(frame(T0 + k * 100 * MS + 7 * MS, [person_box(truth)]))
        events += r.events
    assert [e.event for e in events] == [ObjectEvent.CONFIRMED]
    o = r.objects.objects[0]
    assert o.confirmed and o.hits == 4 and o.class_name == "person"
    np.testing.assert_allclose(o.position_m.to_array(), truth, atol=0.05)
    p = o.position_m
    lat, lon = MapProjection(HOME.latitude_deg, HOME.longitude_deg).reproject(p.y + 2.0, p.x - 1.0)     # about home
    assert (o.latitude_deg, o.longitude_deg) == (pytest.approx(lat, abs=1e-9), pytest.approx(lon, abs=1e-9))
    assert o.altitude_amsl_m == pytest.approx(488.875, abs=0.05)
    assert len(o.position_covariance_m2) == 9 and o.position_covariance_m2[0] > 0
    assert pl.placed == {"ground": 4}


def test_tracks_are_lost_on_the_image_clock_when_frames_stop():
    """Sim time may lag the wall clock (a sim slower than real time): the timeout runs on from the
    last frame's stamp, so a track is lost lost_timeout_s after its last frame arrived, not sooner."""
    pl = pipeline(stereo=False, confirm_hits=2, lost_timeout_s=3.0)
    truth = np.array([20.0, 3.0, 0.875])
    feed_states(pl, T0 + 300 * MS)
    for k in range(3):
        pl.process(frame(T0 + k * 100 * MS, [person_box(truth)]))
    placed_at = pl.last_frame_mono_s
    assert pl.expire(placed_at + 2.5) == []
    lost = pl.expire(placed_at + 3.2)
    assert [(e.event, e.object.track_id) for e in lost] == [(ObjectEvent.LOST, 1)] and pl.tracker.tracks == []
    assert ObjectsPipeline(pl.cfg).expire(1e9) == []                  # no frame yet: nothing to lose


def test_frames_without_a_pose_camera_info_or_in_order_are_counted_not_placed():
    pl = pipeline()
    assert pl.process(frame(T0, [(320, 300, 10, 30)])) is None
    assert pl.dropped["frame_no_pose"] == 1
    feed_states(pl, T0 + 100 * MS)
    assert pl.process(frame(T0 + 2_000 * MS, [(320, 300, 10, 30)])) is None     # 1.9 s after the newest pose
    assert pl.dropped["frame_no_pose"] == 2
    assert pl.process(frame(T0 + 50 * MS, [(320, 300, 10, 30)])) is not None
    assert pl.process(frame(T0 + 30 * MS, [(320, 300, 10, 30)])) is None
    assert pl.dropped["frame_out_of_order"] == 1
    bare = ObjectsPipeline(build(ObjectsConfig, contract.PARAMS))
    assert bare.process(frame(T0, [])) is None and bare.dropped["frame_no_camera_info"] == 1


def stereo_images(stamp_ns, box, disparity_px):
    left, right = textured_pair(disparity_px, box)
    h = Header(stamp_ns=stamp_ns)
    return Image.from_numpy(left, "mono8", h), Image.from_numpy(right, "mono8", h)


def test_the_stereo_pair_of_the_frames_stamp_gives_the_range():
    # Close and low (2 m up, 5 m ahead): disparity 5.1 px, the ground ray is off by the height guess.
    pl = pipeline(height_sigma_m=0.5)
    position = (0.0, 0.0, 2.0)
    truth = np.array([5.0, 0.0, 1.4])                # a tall object: the class table's 0.875 is wrong
    u, v, w, h = person_box(truth, position)
    _, _, z = project(truth, PoseSample(0, np.asarray(position), quat_from_euler(0.0, 0.0, 0.0)), PITCH)
    disp = FX * BASELINE / z
    box = (int(u - w / 2), int(v - h / 2), int(u + w / 2), int(v + h / 2))
    feed_states(pl, T0 + 100 * MS, position)
    stamp = T0 + 50 * MS
    left, right = stereo_images(stamp, box, int(round(disp)))
    pl.on_image("left", left)
    pl.on_image("right", right)
    r = pl.process(frame(stamp, [(u, v, w, h)]))
    assert pl.placed == {"stereo+ground": 1} or pl.placed == {"stereo": 1}
    o = r.objects.objects[0]
    # The integer disparity of the synthetic pair is off by < 0.5 px of 5.1: within ~0.5 m.
    assert abs(o.position_m.x - truth[0]) < 0.6, o.position_m


def test_ten_boxes_a_frame_with_stereo_are_each_placed_and_tracked():
    """Ten boxes a frame, 30 frames: every box placed (stereo searched, ground), ten tracks. The cost (goal < 5 ms
    a frame) is `aero bench objects`' figure, not an assertion here: a timed unit test fails on a
    loaded machine for reasons that are not the code's."""
    # Ten people side by side, ~1 m apart, placed to ~0.2 m (a far placement that uncertain could be its neighbour).
    pl = pipeline(birth_spacing_m=0.5, pixel_sigma_px=0.5, height_sigma_m=0.05, disparity_sigma_px=0.05,
                  position_sigma_m=0.02, attitude_sigma_rad=0.002)
    feed_states(pl, T0 + 3_000 * MS, (0.0, 0.0, 3.0))
    boxes = [(60.0 + 55 * i, 300.0, 30.0, 100.0) for i in range(10)]     # 5-6 m ahead
    ms, cpu_ms = [], []
    for k in range(30):
        stamp = T0 + k * 100 * MS
        left, right = stereo_images(stamp, (300, 265, 324, 335), 4)
        pl.on_image("left", left)
        pl.on_image("right", right)
        r = pl.process(frame(stamp, boxes))
        ms.append(r.elapsed_ms)
        cpu_ms.append(r.cpu_ms)
    cpu = float(np.median(cpu_ms))
    # CPU time, not wall: on the shared 2-core CI the wall clock counts other processes' turns.
    print(f"objects: one frame of 10 boxes (stereo + ground, 10 tracks): CPU p50 {cpu:.2f} ms, "
          f"wall p50 {np.median(ms):.2f} ms")
    assert sum(pl.placed.values()) == 300 and not pl.dropped, (pl.placed, pl.dropped)
    assert len(r.objects.objects) == 10


def test_boxes_touching_the_images_edge_are_marked_cut():
    from aeroperception.services.objects.logic import _cut

    f = frame(T0, [(320, 240, 40, 80), (20, 240, 40, 80), (320, 440, 40, 80), (620, 100, 40, 40)])
    assert [_cut(d, f) for d in f.detections] == [False, True, True, True]
    f.image_width = f.image_height = 0                                   # size unknown: nothing is cut
    assert not any(_cut(d, f) for d in f.detections)


def test_a_frame_placed_at_a_pose_trailing_a_fast_turn_starts_no_second_track():
    """Pitching into a leg (3.5 rad/s) the pose's attitude trails the camera's by ~15 ms: a whole
    frame's ground placements fall metres long (here 5.2, 4.4, 3.6 m at 22 m), a few frames running.
    The turn rate times pose_time_sigma_s widens them like pixel noise: they start no second track
    and do not move the person's (which they did with it off: a duplicate confirmed on the third)."""
    truth = np.array([22.0, -3.0, 0.875])
    found = {}
    for sigma_s in (0.0, 0.02):
        pl = pipeline(stereo=False, confirm_hits=3, pose_time_sigma_s=sigma_s)
        feed_states(pl, T0 + 300 * MS)
        for t in range(T0 + 340 * MS, T0 + 800 * MS, 20 * MS):           # state/vehicle: level, turning fast
            pl.on_state(VehicleState(header=Header(stamp_ns=t), position_m=Vector3(z=10.0),
                                     orientation=Quaternion.from_array(quat_from_euler(0.0, 0.0, 0.0)),
                                     angular_velocity_radps=Vector3(y=3.5)))
        for k in range(4):
            pl.process(frame(T0 + k * 100 * MS, [person_box(truth)]))
        for k, trail_deg in enumerate((4.0, 3.0, 2.0)):                  # the camera already pitched this much
            pl.process(frame(T0 + 400 * MS + k * 50 * MS, [person_box(truth, pitch_rad=np.radians(trail_deg))]))
        found[sigma_s] = [(t.confirmed, t.x[:2]) for t in pl.tracker.tracks]
    assert [c for c, _ in found[0.0]] == [True, True]                      # without: a duplicate, metres long
    assert np.linalg.norm(found[0.0][1][1] - truth[:2]) > 2.5
    (confirmed, xy), = found[0.02]
    assert confirmed and np.linalg.norm(xy - truth[:2]) < 0.1
