"""VIO front end (and the whole strategy) on synthetic scenes with known motion: stereo pairs
rendered by the simulator's own camera along a known trajectory, with its IMU model."""
import numpy as np
import pytest

from aerotest import forward_camera_info

from aeroperception.services.runtime.rotations import quat_to_rotmat
from aeroperception.services.vio.calibration import CameraCalibration
from aeroperception.services.vio.dto import ImuWindow, NavCameraFrame, VioDegradedError, VioInitializingError
from aeroperception.services.vio.frontend import FrontEnd, FrontEndConfig, pnp_covariance
from aeroperception.services.vio.strategy import create_strategy
from aeroperception.tools.bench.vio import sim_sequence
from aeroperception.tools.eval.vio import metrics


def pose(tr) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rotmat(tr.q_enu_flu), tr.position_enu_m
    return T


def run_vio(seq, indices, imu=None, prev_ns: int = -1):
    """A klt_stereo strategy fed the frames `indices` of `seq` and the IMU samples (`imu`, default all)
    since the previous one: (the strategy, [(frame index, output)] for each frame that gave one)."""
    calib = CameraCalibration.from_camera_infos(*seq.camera_infos)
    vio, outs, imu = create_strategy("klt_stereo"), [], seq.imu if imu is None else imu
    for i in indices:
        t = seq.stamps_ns[i]
        window = [s for s in imu if prev_ns < s.t_ns <= t]
        prev_ns = t
        try:
            outs.append((i, vio.process_frame(NavCameraFrame(i, t, seq.left[i], seq.right[i]),
                                              ImuWindow(window[0].t_ns if window else t, t, window), calib)))
        except VioInitializingError:
            continue
        except VioDegradedError as e:
            outs.append((i, e.output))
    return vio, outs


@pytest.fixture(scope="module")
def seq():
    # 0.5 s still, then an orbit ramping up to 2.5 m/s: 4 s of stereo at 20 Hz.
    return sim_sequence(80, scenario="village")


def test_front_end_relative_poses_match_the_known_motion(seq):
    calib = CameraCalibration.from_camera_infos(*seq.camera_infos)
    fe = FrontEnd(calib, FrontEndConfig())
    kf_index, checked = 0, 0
    for i, t in enumerate(seq.stamps_ns):
        res = fe.process(t, seq.left[i], seq.right[i])
        if res.T_kf_cur is not None:
            T_est = calib.T_body_rect @ res.T_kf_cur @ np.linalg.inv(calib.T_body_rect)
            T_true = np.linalg.inv(pose(seq.truth[kf_index])) @ pose(seq.truth[i])
            d = np.linalg.norm(T_true[:3, 3])
            assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) < 0.01 + 0.05 * d, (i, T_est[:3, 3], T_true[:3, 3])
            dR = T_true[:3, :3].T @ T_est[:3, :3]
            assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.5
            assert res.status == "ok" and res.quality.inliers >= 40
            checked += 1
        if res.new_keyframe:
            kf_index = i
    assert checked >= len(seq.stamps_ns) - 2
    # Moving at up to 2.5 m/s, tracks leave the view: keyframes are taken and corners re-detected.
    assert fe.keyframes >= 5
    assert len(fe.kf_px) >= 60


def test_pnp_covariance_shrinks_with_more_points_and_grows_with_depth():
    rng = np.random.default_rng(0)
    near = np.column_stack([rng.uniform(-2, 2, (50, 2)), rng.uniform(3, 6, 50)])
    c_near = pnp_covariance(near, 400.0, 1.0)
    c_far = pnp_covariance(near * [1, 1, 4], 400.0, 1.0)
    c_more = pnp_covariance(np.vstack([near, near + 0.01]), 400.0, 1.0)
    assert np.trace(c_far[3:, 3:]) > 4 * np.trace(c_near[3:, 3:])
    assert np.trace(c_more) < np.trace(c_near)
    assert np.all(np.linalg.eigvalsh(c_near) > 0)


def test_stereo_vio_on_the_rendered_flight_small_drift_and_honest_covariance(seq):
    _, outs = run_vio(seq, range(len(seq.stamps_ns)))
    est, truth = [o for _, o in outs], [pose(seq.truth[i]) for i, _ in outs]
    assert len(est) >= len(seq.stamps_ns) - 5
    m = metrics([e.world_T_body for e in est], truth, [e.pose_covariance_6x6[:3, :3] for e in est],
                [e.stamp_ns for e in est])
    assert m["distance_m"] > 5.0
    assert m["drift_pct"] < 2.0, m
    assert m["ate_rmse_m"] < 0.05, m
    assert 0.3 < m["nees_position_mean"] < 9.0, m


def test_stereo_vio_started_in_flight_tracks_at_once(seq):
    """A restart in flight (no still phase): velocity unknown at first, found from stereo + IMU."""
    start = 40                                   # 2 s in: ~2.5 m/s along the orbit
    assert np.linalg.norm(seq.truth[start].velocity_enu_mps) > 2.0
    vio, outs = run_vio(seq, range(start, len(seq.stamps_ns)), prev_ns=seq.stamps_ns[start] - 300_000_000)
    assert len(outs) == len(seq.stamps_ns) - start             # an output from the first frame on
    est, truth = [o for _, o in outs], [pose(seq.truth[i]) for i, _ in outs]
    assert vio.health_snapshot().state_name == "TRACKING" and vio.counters["resets"] == 0
    m = metrics([e.world_T_body for e in est], truth, [e.pose_covariance_6x6[:3, :3] for e in est],
                [e.stamp_ns for e in est])
    assert m["ate_rmse_m"] < 0.05, m
    # Velocity in the body frame (odom's yaw is VIO's own): found within the run.
    v_est = est[-1].world_T_body[:3, :3].T @ est[-1].velocity_world_mps
    v_true = truth[-1][:3, :3].T @ seq.truth[-1].velocity_enu_mps
    assert np.linalg.norm(v_est - v_true) < 0.3, (v_est, v_true)


def test_a_restart_after_an_imu_gap_in_flight_carries_the_pose_over_the_gap(seq):
    """1.1 s without IMU (and frames) at ~2.5 m/s: the smoother restarts continuing the odom frame
    (reset counter + 1) from the last estimate carried over the gap at its velocity and turn rate,
    not from where the vehicle was before it (a 2.7 m jump back, and the heading it turned)."""
    gap = (1_900_000_000, 3_000_000_000)
    vio, outs = run_vio(seq, [i for i, t in enumerate(seq.stamps_ns) if not gap[0] < t < gap[1]],
                        [s for s in seq.imu if not gap[0] < s.t_ns < gap[1]])
    before = [(o, pose(seq.truth[i])) for i, o in outs if seq.stamps_ns[i] <= gap[0]]
    after = [(o, pose(seq.truth[i])) for i, o in outs if seq.stamps_ns[i] > gap[0]]
    assert vio.counters["resets"] == 1 and len(after) >= 15 and after[-1][0].reset_counter == 1
    # the odom frame as the estimate before the gap placed it (VIO's own start: truth = A @ est)
    A = before[-1][1] @ np.linalg.inv(before[-1][0].world_T_body)
    errors = [np.linalg.norm((A @ o.world_T_body)[:3, 3] - T[:3, 3]) for o, T in after]
    yaw_errors = [abs(np.degrees(np.arctan2(*((A @ o.world_T_body)[:3, :3].T @ T[:3, :3])[[1, 0], 0]))) for o, T in after]
    flown = np.linalg.norm(after[0][1][:3, 3] - before[-1][1][:3, 3])
    print(f"flown in the gap {flown:.2f} m; after the restart position error {errors[0]:.2f} -> {max(errors):.2f} m max, "
          f"yaw error max {max(yaw_errors):.1f} deg")
    # carried at constant velocity and turn rate: 0.68 m off (the orbit speeds up 2.1 -> 2.5 m/s and bends in
    # the gap), 1.1 deg; not carried 2.76 m and 19.9 deg
    assert flown > 2.0
    assert max(errors) < 0.35 * flown, errors
    assert max(yaw_errors) < 3.0, yaw_errors


def _mono_calib() -> CameraCalibration:
    return CameraCalibration.from_camera_infos(forward_camera_info(0.04))


@pytest.mark.parametrize("yaw_deg", [0.0, 3.0])
def test_mono_essential_without_parallax_gives_the_rotation_not_a_solver_error(yaw_deg):
    """A still or purely rotating mono camera: no translation, so no essential matrix (OpenCV 5's
    five-point solver asserts on it); the rotation comes from the bearings instead."""
    from aeroperception.services.vio.frontend import solve_essential
    calib, cfg = _mono_calib(), FrontEndConfig()
    rng = np.random.default_rng(3)
    pts_c = np.column_stack([rng.uniform(-4, 4, 80), rng.uniform(-3, 3, 80), rng.uniform(4, 20, 80)])
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])   # about the camera's y

    def project(p):
        return np.column_stack([calib.f * p[:, 0] / p[:, 2] + calib.cx, calib.f * p[:, 1] / p[:, 2] + calib.cy])

    sol = solve_essential(project(pts_c), project(pts_c @ R.T), calib, cfg)
    assert sol is not None
    T, mask, cov, _sigma = sol
    assert mask.sum() == 80
    assert np.allclose(T[:3, :3], R, atol=1e-6) and np.allclose(T[:3, 3], 0)
    assert cov[3, 3] == 100.0   # translation left to the IMU
