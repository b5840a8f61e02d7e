"""The VioStrategy seam: registry and errors, the health table, and bad inputs (missing
calibration, wrong image size, IMU gaps, time going backwards) giving a clear state, never a crash.

The scene is synthetic: a textured fronto-parallel wall 1.28 m ahead of a still stereo rig
(right image = left shifted by the 20 px disparity), with a still IMU reading +g on body z."""
import cv2
import numpy as np
import pytest

from aerotest import forward_camera_info

from aeroperception.schemas import Pose, Quaternion, Vector3
from aeroperception.services.runtime.rotations import quat_from_rotmat
from aeroperception.services.vio import health as H
from aeroperception.services.vio.calibration import CalibrationError, CameraCalibration
from aeroperception.services.vio.dto import (
    DEGRADED, INIT, LOST, TRACKING, ImuSample, ImuWindow, NavCameraFrame, StrategyNotAvailableError,
    VioDegradedError, VioFatalError, VioInitializingError, WarmStartPose,
)
from aeroperception.services.vio.strategy import STRATEGIES, VioConfig, VioStrategy, create_strategy

W, H_PX, D_PX = 640, 480, 20
DT_NS = 50_000_000


CALIB = CameraCalibration.from_camera_infos(forward_camera_info(0.04), forward_camera_info(-0.04))


def images():
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (H_PX, W + 2 * D_PX)).astype(np.uint8), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    return np.ascontiguousarray(tex[:, D_PX:D_PX + W]), np.ascontiguousarray(tex[:, 2 * D_PX:2 * D_PX + W])


LEFT, RIGHT = images()


class Feeder:
    """Drives a strategy frame by frame with a still IMU (200 Hz) between frames."""

    def __init__(self, strategy: VioStrategy):
        self.s, self.t, self.k, self.imu_t = strategy, 0, 0, -DT_NS

    def imu(self, until_ns: int, skip_until_ns: int | None = None) -> ImuWindow:
        out = []
        while self.imu_t + 5_000_000 <= until_ns:
            self.imu_t += 5_000_000
            if skip_until_ns is None or self.imu_t > skip_until_ns:
                out.append(ImuSample(self.imu_t, np.zeros(3), np.array([0.0, 0.0, 9.80665])))
        return ImuWindow(out[0].t_ns if out else until_ns, until_ns, out)

    def frame(self, left=LEFT, right=RIGHT, calib=CALIB, dt_ns=DT_NS, imu_gap_ns=None):
        self.t += dt_ns
        self.k += 1
        skip = self.t - dt_ns + imu_gap_ns if imu_gap_ns else None   # no samples just after the last frame
        return self.s.process_frame(NavCameraFrame(self.k, self.t, left, right), self.imu(self.t, skip), calib)

    def until_tracking(self, n=20):
        for _ in range(n):
            try:
                out = self.frame()
                if self.s.health_snapshot().state == TRACKING:
                    return out
            except VioInitializingError:
                pass
        raise AssertionError(f"not TRACKING after {n} frames: {self.s.health_snapshot()}")


def test_registry_builds_the_klt_strategies_and_refuses_unbuilt_ones_naming_what_exists():
    assert set(STRATEGIES) == {"klt_stereo", "klt_mono"}
    for name in STRATEGIES:
        assert isinstance(create_strategy(name), VioStrategy)
    for name in ("okvis2", "vins_mono", "orb_slam9"):
        with pytest.raises(StrategyNotAvailableError) as e:
            create_strategy(name)
        assert name in str(e.value) and "klt_stereo" in str(e.value) and "klt_mono" in str(e.value)


def test_health_table_every_transition():
    expected = {
        (INIT, H.INITIALIZED): TRACKING, (TRACKING, H.WEAK): DEGRADED, (TRACKING, H.MISS): DEGRADED,
        (TRACKING, H.MISS_LIMIT): LOST, (DEGRADED, H.GOOD): TRACKING, (DEGRADED, H.MISS_LIMIT): LOST,
        (LOST, H.GOOD): TRACKING, (LOST, H.WEAK): DEGRADED, (LOST, H.MISS): LOST,
    }
    for (state, event), nxt in expected.items():
        assert H.next_state(state, event) == nxt, (state, event)
    for state in (INIT, TRACKING, DEGRADED, LOST):
        assert H.next_state(state, H.RESET) == INIT
    for event in (H.GOOD, H.WEAK, H.MISS, H.MISS_LIMIT):
        assert H.next_state(INIT, event) == INIT   # no output before initialisation
    assert set(H.TRANSITIONS.values()) <= {INIT, TRACKING, DEGRADED, LOST}


def test_still_stereo_rig_initialises_level_and_stays_put():
    f = Feeder(create_strategy("klt_stereo"))
    with pytest.raises(VioInitializingError, match="waiting for IMU"):
        f.frame()
    f.until_tracking()
    for _ in range(20):
        out = f.frame()
    assert np.linalg.norm(out.world_T_body[:3, 3]) < 0.01
    assert np.allclose(out.world_T_body[:3, :3] @ [0, 0, 1], [0, 0, 1], atol=1e-3)   # level: FLU z up
    sig = np.sqrt(np.diag(out.pose_covariance_6x6))
    assert np.all(sig > 0) and sig[:3].max() < 0.05
    assert out.feature_quality.tracked >= 40 and f.s.health_snapshot().state == TRACKING


def test_mono_strategy_tracks_the_same_scene_with_the_left_camera_only():
    calib = CameraCalibration.from_camera_infos(forward_camera_info(0.04))
    f = Feeder(create_strategy("klt_mono"))
    for _ in range(10):
        try:
            f.frame(right=None, calib=calib)
        except VioInitializingError:
            pass
    assert f.s.health_snapshot().state == TRACKING
    with pytest.raises(VioInitializingError, match="stereo"):
        Feeder(create_strategy("klt_stereo")).frame(calib=calib)


def test_missing_calibration_keeps_init_with_a_clear_message():
    f = Feeder(create_strategy("klt_stereo"))
    for _ in range(3):
        with pytest.raises(VioInitializingError, match="calibration"):
            f.frame(calib=None)
    assert f.s.health_snapshot().state == INIT
    assert "calibration" in f.s.health_snapshot().message
    with pytest.raises(CalibrationError, match="distortion model"):
        CameraCalibration.from_camera_infos(forward_camera_info(0.04, model="equidistant"), forward_camera_info(-0.04))
    with pytest.raises(CalibrationError, match="right"):
        CameraCalibration.from_camera_infos(forward_camera_info(-0.04), forward_camera_info(0.04))   # swapped cameras


def test_wrong_image_size_degrades_then_lost_then_recovers():
    cfg = VioConfig(lost_after_frames=5)
    f = Feeder(create_strategy("klt_stereo", cfg))
    with pytest.raises(VioInitializingError):
        f.frame(left=LEFT[:240, :320])   # before init: clear reason, no output
    f.until_tracking()
    small = np.ascontiguousarray(LEFT[:240, :320])
    with pytest.raises(VioDegradedError, match="320x240 but the calibration is 640x480") as e:
        f.frame(left=small)
    assert e.value.output is not None            # IMU keeps the estimate going, covariance grows
    assert f.s.health_snapshot().state == DEGRADED
    for _ in range(3):
        with pytest.raises(VioDegradedError):
            f.frame(left=small)
    with pytest.raises(VioFatalError, match="LOST"):
        f.frame(left=small)
    h = f.s.health_snapshot()
    assert h.state == LOST and h.consecutive_lost == 5
    with pytest.raises(VioFatalError):
        f.frame()   # a good frame starts a new keyframe (no fix yet: still LOST)
    out = f.frame()
    assert f.s.health_snapshot().state == TRACKING and f.s.health_snapshot().consecutive_lost == 0
    assert np.linalg.norm(out.world_T_body[:3, 3]) < 0.05


def test_frame_time_going_backwards_is_dropped_and_a_big_jump_reinitialises():
    f = Feeder(create_strategy("klt_stereo"))
    f.until_tracking()
    f.frame()
    with pytest.raises(VioDegradedError, match="backwards") as e:
        f.frame(dt_ns=-DT_NS)
    assert e.value.output is None
    assert f.s.counters["time_backwards"] == 1
    f.t += DT_NS * 2
    f.frame()
    assert f.s.health_snapshot().state == TRACKING
    f.t -= 5_000_000_000
    f.imu_t = f.t - DT_NS
    with pytest.raises(VioInitializingError, match="jumped back"):
        f.frame()
    assert f.s.health_snapshot().state == INIT
    f.until_tracking()


def test_imu_gap_degrades_a_frame_and_a_long_one_reinitialises():
    f = Feeder(create_strategy("klt_stereo"))
    f.until_tracking()
    with pytest.raises(VioDegradedError, match="IMU gap"):
        f.frame(imu_gap_ns=90_000_000, dt_ns=2 * DT_NS)   # ~95 ms without samples
    assert f.s.health_snapshot().state == DEGRADED
    f.frame()
    assert f.s.health_snapshot().state == TRACKING
    with pytest.raises(VioInitializingError, match="IMU gap"):
        f.frame(dt_ns=1_500_000_000, imu_gap_ns=1_450_000_000)
    assert f.s.health_snapshot().state == INIT and f.s.counters["resets"] == 1


def test_reinitialisation_after_a_long_imu_gap_keeps_yaw_and_position():
    """A restart of the smoother continues the odom frame from the last estimate (yaw included),
    not from the origin with yaw 0: the FC and the mission see no jump."""
    f = Feeder(create_strategy("klt_stereo"))
    f.until_tracking()
    c, s = np.cos(0.6), np.sin(0.6)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [5.0, 1.0, 2.0]
    f.s.reset_to_warm_start(WarmStartPose(T))
    f.until_tracking()
    for _ in range(5):
        f.frame()
    with pytest.raises(VioInitializingError, match="IMU gap"):
        f.frame(dt_ns=1_500_000_000, imu_gap_ns=1_450_000_000)
    out = f.until_tracking()
    for _ in range(5):
        out = f.frame()
    assert np.allclose(out.world_T_body[:3, 3], [5.0, 1.0, 2.0], atol=0.05), out.world_T_body
    yaw = np.arctan2(out.world_T_body[1, 0], out.world_T_body[0, 0])
    assert abs(yaw - 0.6) < 0.01, yaw


def test_quality_band_is_the_health_state_and_the_inliers_place_it():
    q = lambda n, state=TRACKING: H.quality_pct(state, n, good_inliers=40, full_inliers=70)
    assert [q(None), q(0), q(1), q(12), q(39), q(40), q(55), q(70), q(250)] == [1, 1, 2, 15, 49, 50, 75, 100, 100]
    assert [q(None, DEGRADED), q(12, DEGRADED), q(40, DEGRADED), q(250, DEGRADED)] == [1, 15, 49, 49]


def test_outputs_carry_quality_and_a_reset_counter_that_counts_restarts():
    """What fmu sends PX4 as ODOMETRY quality and reset_counter: a good fix high, a frame without a
    fix 1 (the IMU's pose); every re-initialisation (smoother restart, warm start) counts one."""
    cfg = VioConfig(lost_after_frames=5)
    f = Feeder(create_strategy("klt_stereo", cfg))
    out = f.until_tracking()
    assert out.reset_counter == 0 and out.quality_pct >= 50
    out = f.frame()
    assert out.reset_counter == 0 and out.quality_pct >= 50
    with pytest.raises(VioDegradedError) as e:
        f.frame(left=np.ascontiguousarray(LEFT[:240, :320]))       # no visual fix this frame
    assert e.value.output.quality_pct == 1 and e.value.output.reset_counter == 0
    with pytest.raises(VioDegradedError, match="new keyframe"):
        f.frame()                                                  # a good frame: new keyframe, no fix yet
    assert f.frame().quality_pct >= 50
    with pytest.raises(VioDegradedError, match="IMU gap") as e:
        f.frame(imu_gap_ns=90_000_000, dt_ns=2 * DT_NS)             # a good fix through an IMU gap
    assert 2 <= e.value.output.quality_pct <= 49
    with pytest.raises(VioInitializingError, match="IMU gap"):
        f.frame(dt_ns=1_500_000_000, imu_gap_ns=1_450_000_000)
    assert f.until_tracking().reset_counter == 1
    f.s.reset_to_warm_start(WarmStartPose(np.eye(4)))
    assert f.until_tracking().reset_counter == 2 and f.frame().reset_counter == 2


def test_garbage_imu_samples_are_dropped_not_integrated():
    f = Feeder(create_strategy("klt_stereo"))
    f.until_tracking()
    f.t += DT_NS
    f.k += 1
    w = f.imu(f.t)
    w.samples[3] = ImuSample(w.samples[3].t_ns, np.array([np.nan, 0, 0]), np.zeros(3))
    w.samples.append(ImuSample(w.samples[0].t_ns, np.zeros(3), np.zeros(3)))   # duplicate stamp
    out = f.s.process_frame(NavCameraFrame(f.k, f.t, LEFT, RIGHT), w, CALIB)
    assert f.s.counters["imu_dropped"] == 2
    assert np.all(np.isfinite(out.world_T_body))


def test_warm_start_restarts_from_the_given_pose():
    f = Feeder(create_strategy("klt_stereo"))
    f.until_tracking()
    T = np.eye(4)
    T[:3, 3] = [10.0, -2.0, 3.0]
    f.s.reset_to_warm_start(WarmStartPose(T))
    assert f.s.health_snapshot().state == INIT
    out = f.until_tracking()
    assert np.allclose(out.world_T_body[:3, 3], [10.0, -2.0, 3.0], atol=0.01)
    with pytest.raises(VioFatalError):
        f.s.reset_to_warm_start(WarmStartPose(np.full((4, 4), np.nan)))


def test_imu_watermark_lets_the_worker_wait_for_the_imu_up_to_a_frame_bounded():
    import threading

    from aeroperception.services.vio.slot import ImuWatermark

    mark = ImuWatermark()
    mark.put(100)
    assert mark.wait_for(100, 0.0) and mark.waits == 0           # already in: no wait
    late = threading.Timer(0.05, mark.put, args=(250,))            # the IMU callback runs behind
    late.start()
    assert mark.wait_for(200, 2.0) and mark.waits == 1 and mark.timeouts == 0
    mark.put(120)                                                   # older: the mark never goes back
    assert mark.newest_ns == 250
    assert not mark.wait_for(300, 0.05) and mark.timeouts == 1      # missing IMU: bounded, a gap
    late.join()


def test_frame_slot_pairs_by_stamp_and_newest_wins_while_busy():
    from aeroperception.services.vio.slot import FrameSlot

    s = FrameSlot(stereo=True)
    s.put("left", "L1", 1)
    assert s.take(0.0) is None                    # no right image yet
    s.put("right", "R1", 1)
    s.put("left", "L2", 2)
    s.put("right", "R2", 2)                       # worker busy: pair 2 replaces pair 1
    assert s.take(0.0) == ("L2", "R2") and s.dropped == 1
    s.put("left", "L3", 3)
    s.put("left", "L4", 4)                        # L3's right never came
    s.put("right", "R4", 4)
    assert s.take(0.0) == ("L4", "R4") and s.unpaired == 1 and s.frames_in == 4
    mono = FrameSlot(stereo=False)
    mono.put("left", "L", 5)
    assert mono.take(0.0) == ("L", None)


def test_reset_request_maps_to_a_warm_start_and_refuses_bad_poses():
    from aeroperception.schemas import VioResetRequest
    from aeroperception.services.vio.messages import warm_start

    q = quat_from_rotmat(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))   # yaw 90 deg
    req = VioResetRequest(pose=Pose(position=Vector3(x=10.0, y=-2.0, z=3.0), orientation=Quaternion.from_array(q)),
                          velocity_mps=Vector3(x=0.5))
    w = warm_start(req)
    assert np.allclose(w.world_T_body[:3, 3], [10.0, -2.0, 3.0]) and np.allclose(w.world_T_body[:3, 0], [0, 1, 0])
    assert np.allclose(w.velocity_world_mps, [0.5, 0, 0])
    assert np.allclose(warm_start(VioResetRequest()).world_T_body, np.eye(4))   # default: fresh start at the origin
    with pytest.raises(ValueError, match="finite"):
        warm_start(VioResetRequest(pose=Pose(position=Vector3(x=float("nan")))))
    with pytest.raises(ValueError, match="unit quaternion"):
        warm_start(VioResetRequest(pose=Pose(orientation=Quaternion(w=2.0))))


def test_the_parameters_default_to_the_algorithms_own_configuration():
    # The contract reads its defaults from the algorithm's config classes (one home): the strategy
    # built from the default parameters is configured exactly as VioConfig() is.
    from aeroperception.services.runtime.config import build
    from aeroperception.services.vio import contract
    from aeroperception.services.vio.config import VioServiceConfig

    cfg = build(VioServiceConfig, contract.PARAMS)
    assert cfg.strategy_config() == VioConfig()
    assert build(VioServiceConfig, contract.PARAMS, lag_s=2.5).strategy_config().backend.lag_s == 2.5
