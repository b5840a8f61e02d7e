"""`aero eval vio`: how good the VIO is against ground truth.

Live (`--live --duration S`): records state/visual_odometry from the running vio service and
sim/truth/state from the simulator for S seconds and pairs them by stamp (both on the sim clock).
Offline on an EuRoC/ASL folder (`--euroc DIR`): the same strategy the service runs is fed the
dataset's stereo pairs and IMU (the IMU between frames, as the service does) and its estimates
are compared with the dataset's ground truth:

- ATE: RMSE of position after aligning the estimate to the truth (SE3 least squares, Umeyama
  without scale; `--align yaw` aligns yaw + translation only, VIO's unobservable 4 DoF)
- RPE: RMSE of the relative translation error over `--rpe-delta-s` windows
- drift: final position error after aligning on the first pose only, as % of the distance travelled
  (n/a below 0.5 m: a still vehicle has no distance to normalise by)
- NEES: mean of e^T S^-1 e of the position error e and the reported 3x3 position covariance S
  (after the same first-pose alignment): ~3 for an honest filter, >> 3 over-confident.

The first-pose alignment moves and yaws the estimate onto the truth's first pose and nothing
else: VIO's odom frame is free in position and yaw only (roll and pitch are observed from
gravity), as in rpg_trajectory_evaluation's "posyaw" alignment for VIO. Aligning all six DoF on
one pose took that pose's own attitude error as the truth and rotated the whole path by it: on
MH_01, started in motion, the first estimate's tilt is 4.2 deg off (gone five frames later),
which made 3 of the 4 cm "final error" and most of the NEES.
Prints a table, writes <out>/vio_eval.json and <out>/vio_eval.png (top view estimate vs truth,
error over time; matplotlib if installed, else drawn with OpenCV).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class EvalRun:
    estimates: list            # VioOutput per frame with an output
    health_states: list[str]   # per frame fed
    truth_T: list              # 4x4 world_T_body ground truth at each estimate
    wall_s: float = 0.0
    errors: dict[str, int] = field(default_factory=dict)


def run_euroc(folder, strategy: str = "klt_stereo", max_frames: int | None = None) -> EvalRun:
    """Feed an EuRoC folder to a strategy exactly as the service would (per frame: the IMU since
    the previous frame); returns the estimates with the ground-truth poses at their stamps."""
    from aeroperception.services.runtime.rotations import quat_to_rotmat
    from aeroperception.services.vio.calibration import CameraCalibration
    from aeroperception.services.vio.dto import (
        STATE_NAMES, ImuWindow, NavCameraFrame, VioDegradedError, VioError,
    )
    from aeroperception.services.vio.euroc import EurocDataset
    from aeroperception.services.vio.strategy import VioConfig, create_strategy

    ds = EurocDataset(folder)
    vio = create_strategy(strategy, VioConfig(imu=ds.imu_noise()))
    calib = CameraCalibration.from_camera_infos(*ds.camera_infos())
    gt = ds.groundtruth
    run = EvalRun([], [], [])
    prev = None
    t_wall = time.perf_counter()
    for k, t in enumerate(ds.frame_stamps_ns[:max_frames]):
        t = int(t)
        left, right = ds.load_pair(t)
        imu = ds.imu_samples(prev if prev is not None else t - int(1e9), t)
        prev = t
        out = None
        try:
            out = vio.process_frame(NavCameraFrame(k, t, left, right), ImuWindow(imu[0].t_ns if imu else t, t, imu), calib)
        except VioDegradedError as e:
            out = e.output
        except VioError as e:
            run.errors[type(e).__name__] = run.errors.get(type(e).__name__, 0) + 1
        run.health_states.append(STATE_NAMES[vio.health_snapshot().state])
        if out is not None:
            run.estimates.append(out)
            if gt is not None:
                i = gt.index_at(t)
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = quat_to_rotmat(gt.q_wxyz[i]), gt.position_m[i]
                run.truth_T.append(T)
    run.wall_s = time.perf_counter() - t_wall
    return run


# ---------------------------------------------------------------- metrics (pure)


def align_se3(est: np.ndarray, gt: np.ndarray, yaw_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising sum |R est_i + t - gt_i|^2 (Umeyama, no scale); yaw_only: R about z."""
    mu_e, mu_g = est.mean(axis=0), gt.mean(axis=0)
    E, G = est - mu_e, gt - mu_g
    if len(est) < 3 or np.linalg.norm(E) < 1e-6:
        return np.eye(3), mu_g - mu_e
    if yaw_only:
        a = np.sum(E[:, 0] * G[:, 1] - E[:, 1] * G[:, 0])
        b = np.sum(E[:, 0] * G[:, 0] + E[:, 1] * G[:, 1])
        yaw = np.arctan2(a, b)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
    else:
        U, _, Vt = np.linalg.svd(G.T @ E)
        S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ S @ Vt
    return R, mu_g - R @ mu_e


def align_first_pose(est_T0: np.ndarray, gt_T0: np.ndarray) -> np.ndarray:
    """4x4 A (a yaw about world z and a translation) putting est_T0's position on gt_T0's and
    turning it to the same heading: the yaw psi maximising trace(Rz(psi) R_est R_gt^T), well
    defined also when the body x axis points up (MH_01's IMU), where atan2 of the x axis is not."""
    M = est_T0[:3, :3] @ gt_T0[:3, :3].T
    psi = np.arctan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])
    A = np.eye(4)
    A[:3, :3] = [[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]]
    A[:3, 3] = gt_T0[:3, 3] - A[:3, :3] @ est_T0[:3, 3]
    return A


def metrics(est_T: list, gt_T: list, pos_cov: list, stamps_ns: list, align: str = "se3",
            rpe_delta_s: float = 1.0) -> dict:
    pe = np.array([T[:3, 3] for T in est_T])
    pg = np.array([T[:3, 3] for T in gt_T])
    R, t = align_se3(pe, pg, yaw_only=(align == "yaw"))
    err = pe @ R.T + t - pg
    ate = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    # First-pose alignment (position + yaw, see the module docstring): how a live estimate drifts
    # from where it started.
    A = align_first_pose(est_T[0], gt_T[0])
    e0 = np.array([(A @ T)[:3, 3] for T in est_T]) - pg
    dist = float(np.sum(np.linalg.norm(np.diff(pg, axis=0), axis=1)))
    nees = [float(e @ np.linalg.solve(A[:3, :3] @ S @ A[:3, :3].T, e)) for e, S in zip(e0, pos_cov)
            if np.all(np.isfinite(S)) and np.linalg.det(S) > 0]
    ts = np.array(stamps_ns) * 1e-9
    rpe = []
    for i in range(len(ts)):
        j = int(np.searchsorted(ts, ts[i] + rpe_delta_s))
        if j >= len(ts):
            break
        d_est = np.linalg.inv(est_T[i]) @ est_T[j]
        d_gt = np.linalg.inv(gt_T[i]) @ gt_T[j]
        rpe.append(np.linalg.norm((np.linalg.inv(d_gt) @ d_est)[:3, 3]))
    return {
        "frames": len(est_T), "duration_s": float(ts[-1] - ts[0]) if len(ts) else 0.0,
        "distance_m": dist, "align": align, "ate_rmse_m": ate,
        "ate_max_m": float(np.max(np.linalg.norm(err, axis=1))),
        "rpe_rmse_m": float(np.sqrt(np.mean(np.square(rpe)))) if rpe else None, "rpe_delta_s": rpe_delta_s,
        "final_error_m": float(np.linalg.norm(e0[-1])),
        "drift_pct": float(100 * np.linalg.norm(e0[-1]) / dist) if dist >= 0.5 else None,
        "nees_position_mean": float(np.mean(nees)) if nees else None,
        "nees_position_median": float(np.median(nees)) if nees else None,
        "_series": {"t_s": (ts - ts[0]).tolist(), "est_xy": (pe @ R.T + t)[:, :2].tolist(),
                    "gt_xy": pg[:, :2].tolist(), "err_m": np.linalg.norm(err, axis=1).tolist()},
    }


def plot(m: dict, path: Path, title: str) -> str:
    s = m["_series"]
    est, gt, t, err = np.array(s["est_xy"]), np.array(s["gt_xy"]), np.array(s["t_s"]), np.array(s["err_m"])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
        a.plot(gt[:, 0], gt[:, 1], "k-", label="truth")
        a.plot(est[:, 0], est[:, 1], "r-", label="VIO (aligned)")
        a.set_aspect("equal", "datalim"), a.set_xlabel("x [m]"), a.set_ylabel("y [m]"), a.legend()
        a.set_title("top view")
        b.plot(t, err * 100, "r-"), b.set_xlabel("t [s]"), b.set_ylabel("position error [cm]")
        b.set_title(f"ATE RMSE {m['ate_rmse_m'] * 100:.2f} cm")
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        return "matplotlib"
    except ImportError:
        import cv2

        img = np.full((480, 960, 3), 255, np.uint8)
        pts = np.vstack([gt, est])
        lo, span = pts.min(axis=0), max(np.ptp(pts, axis=0).max(), 1e-3)
        to_px = lambda p: np.int32((p - lo) / span * 400 + [40, 40])
        cv2.polylines(img, [to_px(gt).reshape(-1, 1, 2)], False, (0, 0, 0), 2)
        cv2.polylines(img, [to_px(est).reshape(-1, 1, 2)], False, (0, 0, 255), 2)
        if len(t) > 1:
            e = np.column_stack([520 + t / max(t[-1], 1e-9) * 400, 440 - err / max(err.max(), 1e-9) * 380])
            cv2.polylines(img, [np.int32(e).reshape(-1, 1, 2)], False, (0, 0, 255), 2)
        cv2.putText(img, title, (10, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        cv2.imwrite(str(path), img)
        return "opencv"


def table(m: dict) -> str:
    f = lambda v, unit="", scale=1.0, fmt="{:.3f}": "n/a" if v is None else fmt.format(v * scale) + unit
    rows = [("frames", str(m["frames"])), ("duration", f(m["duration_s"], " s", fmt="{:.1f}")),
            ("distance (truth)", f(m["distance_m"], " m", fmt="{:.2f}")),
            (f"ATE RMSE ({m['align']} aligned)", f(m["ate_rmse_m"], " cm", 100, "{:.2f}")),
            ("ATE max", f(m["ate_max_m"], " cm", 100, "{:.2f}")),
            (f"RPE RMSE ({m['rpe_delta_s']:g} s)", f(m["rpe_rmse_m"], " cm", 100, "{:.2f}")),
            ("final error (start-aligned)", f(m["final_error_m"], " cm", 100, "{:.2f}")),
            ("drift", f(m["drift_pct"], " % of distance", fmt="{:.2f}")),
            ("NEES position (mean / median)", f"{f(m['nees_position_mean'], fmt='{:.2f}')} / "
                                              f"{f(m['nees_position_median'], fmt='{:.2f}')}  (honest ~3)")]
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)


def _pose(p) -> np.ndarray:
    from aeroperception.services.runtime.rotations import quat_to_rotmat

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rotmat(p.orientation.to_array()), p.position.to_array()
    return T


def collect_live(session, duration_s: float, prefix: str = "", until_landed: bool = False) -> tuple[list, list, list]:
    """(odometry messages, truth stamps, truth 4x4 poses) recorded for duration_s, or (until_landed)
    until the true vehicle has been armed in the air and is down and disarmed again: one flight."""
    import threading

    from aeroperception.schemas import Odometry, Pose, SchemaError, VehicleState, decode

    from aeroperception.tools.common import FlightWatch

    odom, t_stamps, t_poses, lock, watch = [], [], [], threading.Lock(), FlightWatch()

    def on_odom(sample) -> None:
        try:
            m = decode(sample.payload.to_bytes(), Odometry)
        except SchemaError:
            return
        with lock:
            odom.append(m)

    def on_truth(sample) -> None:
        try:
            m = decode(sample.payload.to_bytes(), VehicleState)
        except SchemaError:
            return
        with lock:
            t_stamps.append(m.header.stamp_ns)
            t_poses.append(_pose(Pose(position=m.position_m, orientation=m.orientation)))
        watch.update(m.armed, m.position_m.z)

    subs = [session.declare_subscriber(prefix + "state/visual_odometry", on_odom),
            session.declare_subscriber(prefix + "sim/truth/state", on_truth)]
    try:
        if until_landed:
            watch.down.wait(duration_s)
        else:
            time.sleep(duration_s)
    finally:
        for s in subs:
            s.undeclare()
    with lock:
        return list(odom), list(t_stamps), list(t_poses)


def _truth_at(ts: np.ndarray, poses: list, stamp_ns: int, max_gap_ns: int = 50_000_000) -> np.ndarray | None:
    """The true pose at `stamp_ns`: its position interpolated between the two truth samples around
    it (at most max_gap_ns apart), the attitude of the nearer. Interpolated, not the nearest sample:
    a truth stream that lost samples on a loaded host (a DROP stream) would otherwise pair an
    estimate with a truth 10-20 ms away, and at 1 m/s that is a centimetre of error charged to the
    estimate (ATE barely moves; NEES, against a sub-centimetre covariance, does)."""
    k = int(np.searchsorted(ts, stamp_ns))
    if k < len(ts) and ts[k] == stamp_ns:
        return poses[k]
    if k == 0 or k == len(ts) or ts[k] - ts[k - 1] > max_gap_ns:
        return None
    f = (stamp_ns - ts[k - 1]) / (ts[k] - ts[k - 1])
    out = np.array(poses[k if f >= 0.5 else k - 1], float, copy=True)
    out[:3, 3] = (1.0 - f) * poses[k - 1][:3, 3] + f * poses[k][:3, 3]
    return out


def _live_metrics(odom: list, t_stamps: list, t_poses: list, align: str, rpe_delta_s: float) -> dict:
    from aeroperception.tools.common import CliError

    if not odom:
        raise CliError("no state/visual_odometry in the window: is the vio service running (aero run vio) "
                       "and TRACKING (aero topic echo state/vio_health)?")
    if not t_stamps:
        raise CliError("no sim/truth/state in the window: live evaluation needs a truth: the simulator, "
                       "or a recording played with its ground truth (aero play euroc DIR)")
    ts = np.array(t_stamps)
    order = np.argsort(ts)
    ts = ts[order]
    est, gt, cov, st = [], [], [], []
    for m in sorted(odom, key=lambda m: m.header.stamp_ns):
        truth = _truth_at(ts, [t_poses[i] for i in order], m.header.stamp_ns)
        if truth is None:
            continue   # no truth around this estimate
        est.append(_pose(m.pose))
        gt.append(truth)
        c = m.pose_covariance.to_numpy()[:3, :3] if m.pose_covariance is not None else np.full((3, 3), np.nan)
        cov.append(c)
        st.append(m.header.stamp_ns)
    if len(est) < 2:
        raise CliError("odometry and truth stamps do not overlap (is vio following sim/clock?)")
    return metrics(est, gt, cov, st, align, rpe_delta_s)


def run(euroc: str | None, out_dir: str, strategy: str = "klt_stereo", align: str = "se3",
        rpe_delta_s: float = 1.0, max_frames: int | None = None, live_args=None) -> int:
    from aeroperception.tools.common import CliError, open_client

    if live_args is not None:
        session = open_client(live_args)
        try:
            prefix = f"{live_args.vehicle}/" if live_args.vehicle else ""
            until = getattr(live_args, "until_landed", False)
            print(f"recording state/visual_odometry and sim/truth/state for {live_args.duration:g} s"
                  + (" at most, until the vehicle has flown and landed" if until else "") + " ...", flush=True)
            m = _live_metrics(*collect_live(session, live_args.duration, prefix, until), align, rpe_delta_s)
        finally:
            session.close()
        m.update(source="live")
        return _report(m, Path(out_dir), "live VIO vs sim/truth/state")
    if not euroc:
        raise CliError("give a source: aero eval vio --euroc DIR (EuRoC/ASL folder with mav0/) or "
                       "--live (the running vio against sim/truth/state)")
    from aeroperception.services.vio.dto import StrategyNotAvailableError

    try:
        r = run_euroc(euroc, strategy, max_frames)
    except FileNotFoundError as e:
        raise CliError(f"{e}: point --euroc at a folder containing mav0/cam0, mav0/cam1, mav0/imu0") from None
    except StrategyNotAvailableError as e:
        raise CliError(str(e)) from None
    if not r.estimates:
        raise CliError(f"the VIO produced no estimate on {euroc} (health: {r.health_states[-1:]}, errors: {r.errors})")
    if not r.truth_T:
        raise CliError(f"{euroc} has no ground truth (mav0/state_groundtruth_estimate0/data.csv)")
    m = metrics([e.world_T_body for e in r.estimates], r.truth_T,
                [e.pose_covariance_6x6[:3, :3] for e in r.estimates], [e.stamp_ns for e in r.estimates],
                align, rpe_delta_s)
    tim = np.array([e.timings_ms.get("total", np.nan) for e in r.estimates])
    m.update(strategy=strategy, dataset=str(Path(euroc).resolve()), wall_s=r.wall_s,
             frames_fed=len(r.health_states), final_health=r.health_states[-1],
             frame_ms_median=float(np.nanmedian(tim)), errors=r.errors)
    print(f"VIO evaluation: {strategy} on {euroc} ({len(r.health_states)} frames fed, "
          f"final health {r.health_states[-1]}, {m['frame_ms_median']:.1f} ms/frame median)")
    return _report(m, Path(out_dir), f"{strategy} on {Path(euroc).name}")


def _report(m: dict, out: Path, title: str) -> int:
    out.mkdir(parents=True, exist_ok=True)
    series = m.pop("_series")
    (out / "vio_eval.json").write_text(json.dumps({**m, "series": series}, indent=1))
    how = plot({**m, "_series": series}, out / "vio_eval.png", title)
    print(table(m))
    print(f"  wrote {out / 'vio_eval.json'} and {out / 'vio_eval.png'} ({how})")
    return 0
