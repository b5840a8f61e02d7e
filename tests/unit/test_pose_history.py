"""The one PoseHistory (services/lib/pose_history.py) lidar and objects place their samples with:
interpolated at a stamp (objects), nearest as it is (lidar), refused beyond the tolerance, sorted
against duplicates and out-of-order samples, started over when the clock goes back."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from aeroperception.schemas import Header, Quaternion, Vector3, VehicleState
from aeroperception.services.lib.pose_history import PoseHistory, PoseSample
from aeroperception.services.runtime.rotations import quat_from_euler, quat_to_euler, quat_to_rotmat

MS = 1_000_000


def state(stamp_ns, x, yaw=0.0) -> VehicleState:
    return VehicleState(header=Header(stamp_ns=stamp_ns), position_m=Vector3(x=x, z=10.0),
                        orientation=Quaternion.from_array(quat_from_euler(0.0, 0.0, yaw)),
                        angular_velocity_radps=Vector3(z=0.5))


def test_pose_history_interpolates_at_the_images_stamp_and_refuses_beyond_tolerance():
    h = PoseHistory(horizon_s=3.0)
    for i in range(11):                                            # 50 Hz, x = 1 m/s * t, yaw 0 -> 0.2
        h.add(state(i * 20 * MS, i * 0.02, yaw=i * 0.02))
    p = h.at(110 * MS, tolerance_s=0.05)
    assert p.position_m[0] == pytest.approx(0.11)
    assert quat_to_euler(p.q_enu_flu)[2] == pytest.approx(0.11, abs=1e-4)
    assert p.rate_radps == pytest.approx(0.5)
    assert h.at(240 * MS, 0.05) is not None                        # 40 ms after the newest: within tolerance
    assert h.at(260 * MS, 0.05) is None                            # 60 ms: refused
    assert h.at(-60 * MS, 0.05) is None
    h.add(state(400 * MS, 0.4))                                    # a 200 ms gap: nothing to interpolate in it
    assert h.at(300 * MS, 0.05) is None
    h.add(state(100 * MS, 9.9))                                    # out of order: ignored
    assert h.at(100 * MS, 0.05).position_m[0] == pytest.approx(0.1)


def test_nearest_takes_the_closest_sample_as_it_is_within_max_age():
    h = PoseHistory(horizon_s=2.0)
    for i in range(5):                                             # 0, 20, .. 80 ms
        h.add(state(i * 20 * MS, float(i), yaw=0.1 * i))
    p = h.nearest(27 * MS, max_age_s=0.1)
    assert p.stamp_ns == 20 * MS and p.position_m[0] == 1.0        # not interpolated
    np.testing.assert_allclose(p.r_world_body, quat_to_rotmat(quat_from_euler(0.0, 0.0, 0.1)))
    assert h.nearest(33 * MS, 0.1).stamp_ns == 40 * MS
    assert h.nearest(-5 * MS, 0.1).stamp_ns == 0
    assert h.nearest(180 * MS, 0.1).stamp_ns == 80 * MS            # 100 ms after the newest: still within
    assert h.nearest(181 * MS, 0.1) is None
    assert PoseHistory().nearest(0, 1.0) is None
    assert h and not PoseHistory()                                 # "any pose yet?" (objects' health)


def test_old_poses_leave_after_the_horizon():
    h = PoseHistory(horizon_s=1.0)
    for i in range(31):                                            # 0 .. 3 s at 10 Hz
        h.add(state(i * 100 * MS, float(i)))
    assert len(h) == 11                                            # 2.0 .. 3.0 s
    assert h.nearest(1_500 * MS, 0.4) is None
    assert h.nearest(1_900 * MS, 0.4).stamp_ns == 2_000 * MS


def test_a_clock_that_goes_back_starts_the_history_over():
    h = PoseHistory(horizon_s=1.0)
    for i in range(20):
        h.add(state(50_000 * MS + i * 100 * MS, 5.0))
    h.add(state(10 * MS, 0.0))                                     # the simulator restarted: t back to ~0
    assert len(h) == 1
    assert h.at(10 * MS, 0.05).position_m[0] == 0.0
    assert h.nearest(50_000 * MS, 1.0) is None                     # nothing of the old time line is left
    h.add(state(20 * MS, 1.0))
    assert h.at(15 * MS, 0.05).position_m[0] == pytest.approx(0.5)


def test_samples_added_while_another_thread_asks_stay_sorted():
    h = PoseHistory(horizon_s=0.5)
    stop = threading.Event()
    seen = []

    def ask():
        while not stop.is_set():
            p = h.nearest(10**12, 10**4)
            seen.append(p is not None)

    t = threading.Thread(target=ask)
    t.start()
    for i in range(2000):
        h.add_sample(PoseSample(i * MS, np.zeros(3), np.array([1.0, 0, 0, 0])))
    stop.set()
    t.join()
    stamps = [h.nearest(i * MS, 0.0) for i in range(1500, 2000)]
    assert all(p is not None and p.stamp_ns == (1500 + k) * MS for k, p in enumerate(stamps))
