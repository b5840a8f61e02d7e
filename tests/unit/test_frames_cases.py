"""NED/FRD <-> ENU/FLU (services/mavlink/frames.py) and the PX4/ArduPilot mode maps
(services/mavlink/px4.py): hand-worked cases, seeded property round trips, every mode.

Companion to test_frames.py; uses only the conversion names the fmu service calls, and an
independent quaternion -> matrix in this file as the reference.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import Quaternion
from aeroperception.services.mavlink import frames
from aeroperception.services.mavlink.px4 import ARDUCOPTER_MODES, PX4_MODES, Autopilot

SEED = 8780
DEG = math.pi / 180
FORWARD = np.array([1.0, 0.0, 0.0])


def rot(q) -> np.ndarray:
    """Reference body->world rotation matrix of a (w, x, y, z) Hamilton quaternion."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def q_euler(roll, pitch, yaw) -> np.ndarray:
    """ZYX Euler -> quaternion; the formula is frame-agnostic (NED/FRD or ENU/FLU)."""
    return Quaternion.from_euler(roll, pitch, yaw).to_array()


def same_rotation(a, b, atol=1e-9) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.allclose(a, b, atol=atol) or np.allclose(a, -b, atol=atol)


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ================================================================ hand-worked cases

def test_point_ned_1_2_minus3_is_enu_2_1_3():
    np.testing.assert_array_equal(frames.ned_to_enu(np.array([1.0, 2.0, -3.0])), [2.0, 1.0, 3.0])
    np.testing.assert_array_equal(frames.enu_to_ned(np.array([2.0, 1.0, 3.0])), [1.0, 2.0, -3.0])


def test_body_vector_frd_to_flu_negates_y_and_z():
    np.testing.assert_array_equal(frames.frd_to_flu(np.array([1.0, 2.0, 3.0])), [1.0, -2.0, -3.0])
    np.testing.assert_array_equal(frames.flu_to_frd(np.array([1.0, -2.0, -3.0])), [1.0, 2.0, 3.0])


def test_px4_level_heading_north_is_enu_yaw_pi_over_2():
    q = frames.q_ned_frd_to_enu_flu(np.array([1.0, 0.0, 0.0, 0.0]))
    roll, pitch, yaw = frames.euler_from_q(q)
    assert yaw == pytest.approx(math.pi / 2)
    assert roll == pytest.approx(0.0, abs=1e-12) and pitch == pytest.approx(0.0, abs=1e-12)
    assert same_rotation(q, [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(rot(q) @ FORWARD, [0.0, 1.0, 0.0], atol=1e-12)  # nose points North


def test_px4_level_heading_east_is_enu_yaw_0():
    q_ned = q_euler(0.0, 0.0, math.pi / 2)                  # NED heading +90 deg = East
    q = frames.q_ned_frd_to_enu_flu(q_ned)
    assert frames.yaw_from_q(q) == pytest.approx(0.0, abs=1e-12)
    assert same_rotation(q, [1.0, 0.0, 0.0, 0.0])
    assert same_rotation(frames.q_enu_flu_to_ned_frd(np.array([1.0, 0, 0, 0])), q_ned)


def test_px4_heading_west_is_enu_yaw_pi():
    q = frames.q_ned_frd_to_enu_flu(q_euler(0.0, 0.0, -math.pi / 2))
    assert abs(frames.yaw_from_q(q)) == pytest.approx(math.pi)


def test_nose_up_10_deg_in_ned_frd_is_negative_pitch_in_flu():
    q_ned = q_euler(0.0, 10 * DEG, 0.0)                     # heading North, nose 10 deg up
    q = frames.q_ned_frd_to_enu_flu(q_ned)
    roll, pitch, yaw = frames.euler_from_q(q)
    # ROS/FLU: rotation about +y (Left) with positive angle pitches the nose DOWN
    assert pitch == pytest.approx(-10 * DEG)
    assert roll == pytest.approx(0.0, abs=1e-12)
    assert yaw == pytest.approx(math.pi / 2)
    nose = rot(q) @ FORWARD                                   # physically: the nose points up-North
    np.testing.assert_allclose(nose, [0.0, math.cos(10 * DEG), math.sin(10 * DEG)], atol=1e-12)


def test_right_wing_down_20_deg_is_positive_roll_in_both_conventions():
    q = frames.q_ned_frd_to_enu_flu(q_euler(20 * DEG, 0.0, 0.0))
    roll, pitch, _ = frames.euler_from_q(q)
    assert roll == pytest.approx(20 * DEG) and pitch == pytest.approx(0.0, abs=1e-12)
    left_wing = rot(q) @ np.array([0.0, 1.0, 0.0])
    assert left_wing[2] > 0                                   # left wing up


@pytest.mark.parametrize(("roll", "pitch", "yaw"), [
    (0.0, 0.0, 0.0), (0.0, 0.0, 30.0), (0.0, 10.0, 0.0), (15.0, -5.0, 200.0), (-40.0, 25.0, -120.0),
])
def test_body_forward_rotated_by_the_converted_quaternion_is_the_converted_ned_forward(roll, pitch, yaw):
    q_ned = q_euler(roll * DEG, pitch * DEG, yaw * DEG)
    q_enu = frames.q_ned_frd_to_enu_flu(q_ned)
    fwd_ned = rot(q_ned) @ FORWARD                            # FRD forward == FLU forward
    np.testing.assert_allclose(rot(q_enu) @ FORWARD, frames.ned_to_enu(fwd_ned), atol=1e-12)


def test_converted_quaternion_is_the_frame_change_of_the_rotation_matrix():
    p = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])     # v_enu = P v_ned
    b = np.diag([1.0, -1, -1])                               # v_flu = B v_frd
    q_ned = q_euler(0.3, -0.2, 1.1)
    np.testing.assert_allclose(rot(frames.q_ned_frd_to_enu_flu(q_ned)), p @ rot(q_ned) @ b, atol=1e-12)


@pytest.mark.parametrize(("yaw_ned", "yaw_enu"), [
    (0.0, math.pi / 2), (math.pi / 2, 0.0), (math.pi / 4, math.pi / 4), (-math.pi / 2, -math.pi),
    (math.pi, -math.pi / 2), (3 * math.pi / 4, -math.pi / 4),
])
def test_yaw_by_hand(yaw_ned, yaw_enu):
    got = frames.yaw_ned_to_enu(yaw_ned)
    assert -math.pi <= got < math.pi
    assert got == pytest.approx(yaw_enu)


def test_pose_covariance_by_hand():
    c = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    c[0, 2] = c[2, 0] = 0.5                                  # North-Down
    c[3, 5] = c[5, 3] = 0.25                                 # roll-yaw (FRD)
    e = frames.cov6_ned_frd_to_enu_flu(c)
    assert np.diag(e).tolist() == pytest.approx([2.0, 1.0, 3.0, 4.0, 5.0, 6.0])
    assert e[1, 2] == pytest.approx(-0.5)                    # North-Up
    assert e[0, 2] == pytest.approx(0.0)
    assert e[3, 5] == pytest.approx(-0.25)                   # roll-yaw (FLU: yaw sign flips)


# ================================================================ seeded properties

def test_vector_round_trips_preserve_length_and_handedness():
    rng = np.random.default_rng(SEED)
    a, b = rng.normal(size=(200, 3)) * 50, rng.normal(size=(200, 3)) * 50
    np.testing.assert_allclose(frames.enu_to_ned(frames.ned_to_enu(a)), a)
    np.testing.assert_allclose(frames.ned_to_enu(frames.enu_to_ned(a)), a)
    np.testing.assert_allclose(frames.flu_to_frd(frames.frd_to_flu(a)), a)
    np.testing.assert_allclose(np.linalg.norm(frames.ned_to_enu(a), axis=1), np.linalg.norm(a, axis=1))
    # proper rotations, not reflections: they commute with the cross product
    np.testing.assert_allclose(frames.ned_to_enu(np.cross(a, b)),
                               np.cross(frames.ned_to_enu(a), frames.ned_to_enu(b)), atol=1e-9)
    np.testing.assert_allclose(frames.frd_to_flu(np.cross(a, b)),
                               np.cross(frames.frd_to_flu(a), frames.frd_to_flu(b)), atol=1e-9)


def test_quaternion_round_trips_and_agrees_with_vector_conversions():
    rng = np.random.default_rng(SEED + 1)
    for q_ned in random_quats(rng, 200):
        q_enu = frames.q_ned_frd_to_enu_flu(q_ned)
        assert np.linalg.norm(q_enu) == pytest.approx(1.0)
        assert same_rotation(frames.q_enu_flu_to_ned_frd(q_enu), q_ned)
        v_frd = rng.normal(size=3)
        np.testing.assert_allclose(rot(q_enu) @ frames.frd_to_flu(v_frd),
                                   frames.ned_to_enu(rot(q_ned) @ v_frd), atol=1e-9)


def test_yaw_round_trips_and_matches_the_attitude_yaw():
    rng = np.random.default_rng(SEED + 2)
    for y in rng.uniform(-10.0, 10.0, size=300):
        back = frames.yaw_enu_to_ned(frames.yaw_ned_to_enu(y))
        assert math.cos(back) == pytest.approx(math.cos(y), abs=1e-9)
        assert math.sin(back) == pytest.approx(math.sin(y), abs=1e-9)
    for _ in range(200):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
        q_enu = frames.q_ned_frd_to_enu_flu(q_euler(roll, pitch, yaw))
        got, want = frames.yaw_from_q(q_enu), frames.yaw_ned_to_enu(yaw)
        assert math.cos(got - want) == pytest.approx(1.0, abs=1e-9)


def test_covariances_stay_symmetric_psd_with_the_same_spectrum_and_round_trip():
    rng = np.random.default_rng(SEED + 3)
    for _ in range(100):
        a = rng.normal(size=(6, 6))
        c = a @ a.T + 1e-3 * np.eye(6)
        for fwd, back in ((frames.cov6_ned_frd_to_enu_flu, frames.cov6_enu_flu_to_ned_frd),
                          (frames.cov6_frd_to_flu, frames.cov6_flu_to_frd)):
            out = fwd(c)
            np.testing.assert_allclose(out, out.T, atol=1e-12)
            np.testing.assert_allclose(np.linalg.eigvalsh(out), np.linalg.eigvalsh(c), rtol=1e-9, atol=1e-12)
            assert np.linalg.eigvalsh(out).min() > 0
            np.testing.assert_allclose(back(out), c, atol=1e-12)


def test_twist_covariance_transforms_like_the_vectors_it_describes():
    rng = np.random.default_rng(SEED + 4)
    samples = rng.normal(size=(20_000, 6)) @ rng.normal(size=(6, 6))
    c_frd = np.cov(samples.T)
    flu = np.hstack([frames.frd_to_flu(samples[:, :3]), frames.frd_to_flu(samples[:, 3:])])
    np.testing.assert_allclose(frames.cov6_frd_to_flu(c_frd), np.cov(flu.T), atol=1e-9)


# ================================================================ flight modes

PX4 = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_PX4)
APM = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)


@pytest.mark.parametrize("name", sorted(PX4_MODES))
def test_every_px4_mode_encodes_as_main_shl16_or_sub_shl24_and_decodes_back(name):
    main, sub = PX4_MODES[name]
    cm = PX4.custom_mode(name)
    assert cm == (main << 16) | (sub << 24)
    assert PX4.mode_name(cm) == name
    assert PX4.custom_mode(name.lower()) == cm
    assert PX4.set_mode_params(name) == (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub))


@pytest.mark.parametrize(("name", "value"), [
    ("LAND", 0x06040000), ("OFFBOARD", 0x00060000), ("HOLD", 0x03040000), ("RTL", 0x05040000),
    ("TAKEOFF", 0x02040000), ("MISSION", 0x04040000), ("POSCTL", 0x00030000),
])
def test_px4_custom_mode_by_hand(name, value):
    assert PX4.custom_mode(name) == value
    assert PX4.mode_name(value) == name


def test_px4_main_modes_without_sub_modes_ignore_the_sub_byte():
    assert PX4.mode_name((6 << 16) | (3 << 24)) == "OFFBOARD"


def test_px4_unknown_values_and_names():
    assert PX4.mode_name(99 << 16) not in PX4_MODES
    assert PX4.mode_name((4 << 16) | (77 << 24)) not in PX4_MODES
    with pytest.raises(KeyError):
        PX4.custom_mode("WARP")


def test_autopilot_is_chosen_from_the_heartbeat():
    assert PX4.name == "px4" and APM.name == "ardupilot"
    assert Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_GENERIC).name == "px4"


@pytest.mark.parametrize(("name", "number"), [
    ("OFFBOARD", 4), ("HOLD", 5), ("LAND", 9), ("RTL", 6), ("MISSION", 3), ("POSCTL", 16),
    ("ALTCTL", 2), ("STABILIZED", 0), ("SMART_RTL", 21),
])
def test_ardupilot_copter_map_by_hand(name, number):
    assert APM.custom_mode(name) == number
    assert APM.mode_name(number) == name
    assert APM.set_mode_params(name) == (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(number), 0.0)


@pytest.mark.parametrize("name", sorted(ARDUCOPTER_MODES))
def test_ardupilot_round_trip_for_every_mode(name):
    decoded = APM.mode_name(APM.custom_mode(name))
    # BRAKE holds position like LOITER: it may read back as HOLD
    assert decoded == name or (name == "BRAKE" and decoded == "HOLD")


def test_ardupilot_unknown_mode():
    assert APM.mode_name(250) not in ARDUCOPTER_MODES
    with pytest.raises(KeyError):
        APM.custom_mode("WARP")
