"""IMU-rate odometry between frames (services/vio/propagate.py): the newest estimate carried forward
with the IMU, stamped at IMU samples, at the asked rate; a later frame's estimate (stamped in the past)
takes over and is carried over the samples since; nothing beyond the horizon or after a reset.

Truth is closed form: a level vehicle facing yaw 0.3 rad, moving at 1 m/s East and accelerating
0.5 m/s^2 East, IMU at 200 Hz (specific force = R^T (a + g))."""
import numpy as np

from aeroperception.services.vio.dto import FeatureQuality, ImuBias, ImuSample, VioOutput
from aeroperception.services.vio.imu import GRAVITY_MPS2, ImuNoise
from aeroperception.services.vio.propagate import ImuPropagator

YAW = 0.3
R = np.array([[np.cos(YAW), -np.sin(YAW), 0.0], [np.sin(YAW), np.cos(YAW), 0.0], [0.0, 0.0, 1.0]])
P0, V0, A = np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.0, 0.0])
IMU_DT_NS = 5_000_000


def truth(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    return P0 + V0 * t_s + 0.5 * A * t_s ** 2, V0 + A * t_s


def estimate(t_s: float, quality: int = 90, resets: int = 0) -> VioOutput:
    T = np.eye(4)
    T[:3, :3], (T[:3, 3], v) = R, truth(t_s)
    return VioOutput(frame_id=1, stamp_ns=round(t_s * 1e9), relative_pose_T=np.eye(4),
                     pose_covariance_6x6=np.eye(6) * 1e-4, imu_bias=ImuBias(), feature_quality=FeatureQuality(),
                     world_T_body=T, velocity_world_mps=v, angular_velocity_body_radps=np.zeros(3),
                     twist_covariance_6x6=np.eye(6) * 1e-4, reset_counter=resets, quality_pct=quality)


def imu(k: int) -> ImuSample:
    return ImuSample(k * IMU_DT_NS, np.zeros(3), R.T @ (A + [0.0, 0.0, GRAVITY_MPS2]))


def feed(prop: ImuPropagator, ks) -> list[VioOutput]:
    return [o for k in ks if (o := prop.on_imu(imu(k))) is not None]


def test_the_estimate_is_carried_forward_at_imu_stamps_at_the_asked_rate():
    prop = ImuPropagator(ImuNoise(), rate_hz=50.0)
    feed(prop, range(0, 10))                      # IMU before any estimate: nothing to carry
    prop.on_estimate(estimate(0.045))
    outs = feed(prop, range(10, 210))             # 0.05 - 1.045 s
    stamps = np.array([o.stamp_ns for o in outs])
    assert np.all(np.diff(stamps) >= 20_000_000) and 45 <= len(outs) <= 51     # 50 Hz from 200 Hz
    assert all(s % IMU_DT_NS == 0 for s in stamps)                              # at IMU samples
    last = outs[-1]
    p, v = truth(last.stamp_ns * 1e-9)
    assert np.allclose(last.world_T_body[:3, 3], p, atol=2e-3) and np.allclose(last.velocity_world_mps, v, atol=2e-3)
    assert np.allclose(last.world_T_body[:3, :3], R, atol=1e-6)
    assert (last.quality_pct, last.reset_counter) == (90, 0)     # the estimate's own
    # uncertainty grows with the time carried (velocity uncertainty x dt, IMU noise)
    assert outs[-1].pose_covariance_6x6[0, 0] > outs[0].pose_covariance_6x6[0, 0] > 1e-4
    assert prop.counters["propagated"] == len(outs)


def test_a_later_frames_estimate_in_the_past_takes_over_over_the_samples_since():
    """Frames are processed late: their estimate is stamped at exposure, behind the newest IMU
    sample. It replaces the base and is carried over the buffered samples, so the next output is
    that estimate at the IMU's time, not a jump back to the exposure time."""
    prop = ImuPropagator(ImuNoise(), rate_hz=200.0)
    prop.on_estimate(estimate(0.0))
    feed(prop, range(0, 100))                     # to 0.495 s
    late = estimate(0.2)
    late.world_T_body = late.world_T_body.copy()
    late.world_T_body[0, 3] += 0.1                # the frame corrects x by 10 cm
    prop.on_estimate(late)
    out = prop.on_imu(imu(100))
    p, _ = truth(0.5)
    assert out.stamp_ns == 500_000_000
    assert np.allclose(out.world_T_body[:3, 3], p + [0.1, 0.0, 0.0], atol=2e-3)
    prop.on_estimate(estimate(0.1))               # older than the base: ignored
    out = prop.on_imu(imu(101))
    assert np.allclose(out.world_T_body[:3, 3], truth(0.505)[0] + [0.1, 0.0, 0.0], atol=2e-3)


def test_nothing_past_the_horizon_after_a_reset_or_from_an_imu_sample_out_of_order():
    prop = ImuPropagator(ImuNoise(), rate_hz=200.0, max_horizon_s=0.5)
    prop.on_estimate(estimate(0.0))
    outs = feed(prop, range(0, 200))
    assert max(o.stamp_ns for o in outs) <= 500_000_000 and prop.counters["beyond_horizon"] == 99
    assert prop.on_imu(imu(150)) is None and prop.counters["imu_out_of_order"] == 1
    prop.on_estimate(estimate(0.99))
    assert prop.on_imu(imu(200)) is not None
    prop.reset()                                   # the VIO restarts: nothing to carry forward
    assert feed(prop, range(201, 220)) == []
    prop.on_estimate(estimate(1.1, resets=1))
    assert prop.on_imu(imu(221)).reset_counter == 1


def test_an_imu_clock_going_back_starts_over():
    """A replay or simulator restart: the IMU clock jumps back; the old samples and base are dropped
    (not every new sample refused as out of order) and the next estimate is carried forward."""
    prop = ImuPropagator(ImuNoise(), rate_hz=200.0)
    prop.on_estimate(estimate(10.0))
    assert feed(prop, range(2000, 2010)) != []
    assert feed(prop, range(0, 5)) == [] and prop.counters["imu_restarts"] == 1
    prop.on_estimate(estimate(0.022))
    out = prop.on_imu(imu(5))
    assert out is not None and out.stamp_ns == 25_000_000
    assert np.allclose(out.world_T_body[:3, 3], truth(0.025)[0], atol=1e-3)

