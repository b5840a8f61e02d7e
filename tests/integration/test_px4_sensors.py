"""Rendered sensors for real PX4: `aero up --profile px4` with the simulator in follow mode (sim
--follow renders the village's stereo camera and LiDAR from SIH's ground truth, which fmu
republishes as fmu/out/vehicle_ground_truth on the clock of PX4's IMU) and VIO and LiDAR on them.
One PX4 + stack serve the module.

Judged by PX4's SIH: its ground truth through fmu (ENU about PX4's local origin), the IMU PX4
sends (sensors/imu via fmu), and where the scenario puts its objects.

- camera: frames at rate, every image stamp inside the FC's IMU stream (on its clock);
- LiDAR: the lidar service, placing scans with PX4's own estimate, sees a street light and a
  building face of the village where the scenario (and truth) puts them; in flight its costmap
  (only marked in the air) has the street light lethal there;
- VIO: a short hop (take-off to 3 m, 5 m East, land) tracked against SIH's truth (ATE after a
  yaw + translation alignment: VIO's frame starts where and as it initialised), and the truth's
  stamps measured against PX4's gyro (diagnostics/sim truth_imu_lag_ms);
- fmu kill -9: no ground truth, the simulator says so and renders nothing; frames resume with fmu.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest

from aerotest import aero_argv, clean_env, wait_until
from aeroperception.schemas import (
    DiagnosticStatus, Image, Imu, OccupancyGrid, Odometry, PointCloud, VehicleState, VioHealth,
)
from aeroperception.tools.eval.vio import align_se3
from test_px4 import px4_up, wait_px4_ready

pytestmark = [pytest.mark.px4, pytest.mark.slow]

SERVICES = ["px4", "fmu", "planner", "mission", "diagnostics", "sim", "vio", "lidar"]
POLE = np.array([5.0, 7.0])                 # village: the street light nearest the pad (radius 0.12 m)
FACADE_Y_M, FACADE_X_M = 10.0, (5.0, 19.0)  # village: south face of the building at (12, 15), 14 x 10 m
HOP = {"mission_id": "px4_sensors_hop", "takeoff_altitude_m": 3.0, "waypoint_acceptance_radius_m": 0.5,
       "waypoints": [{"x": 0.0, "y": 0.0, "z": 3.0, "yaw_deg": 90.0}, {"x": 5.0, "y": 0.0, "z": 3.0, "yaw_deg": 90.0}]}


@pytest.fixture(scope="module")
def px4s(stack_module, px4_build, tmp_path_factory):
    state_dir = tmp_path_factory.mktemp("mission-state")
    with px4_up(stack_module, px4_build, SERVICES, [
            "--scenario", "village", "--arg", f"mission:--param=state_dir={state_dir}",
            # 1 m/s: with the camera at 0.5-4 Hz on a loaded machine consecutive frames still overlap
            "--arg", "planner:--param=max_velocity_mps=1.0"]) as st:
        wait_px4_ready(st)
        try:
            wait_until(lambda: st.latest("fmu/out/vehicle_ground_truth", VehicleState, 2.0), 20, "PX4's ground truth via fmu")
            # the render processes import Open3D and build the scene first: 20-60 s on a loaded machine
            wait_until(lambda: st.latest("sensors/camera/left/image", Image, 2.0), 150, "the first rendered image")
        except BaseException:
            print(st.describe())
            raise
        yield st


def test_px4_camera_frames_at_rate_stamped_on_the_fc_imu_clock(px4s):
    st = px4s
    with st.capture(img=("sensors/camera/left/image", Image), right=("sensors/camera/right/image", Image),
                    imu=("sensors/imu", Imu)) as rec:
        wait_until(lambda: len(rec.get("img")) >= 5, 20, "5 left images")
        t0, n0 = time.monotonic(), len(rec.get("img"))
        time.sleep(4.0)
        rate_hz = (len(rec.get("img")) - n0) / (time.monotonic() - t0)
        imgs, imu = rec.get("img"), np.array([m.header.stamp_ns for m in rec.get("imu")])
        right = {m.header.stamp_ns for m in rec.get("right")}
    d = st.diag("sim")
    gaps_ms = []
    for m in imgs:
        k = int(np.searchsorted(imu, m.header.stamp_ns, side="right"))
        if 0 < k < len(imu):                     # inside the IMU stream: from the IMU sample before it
            gaps_ms.append((m.header.stamp_ns - imu[k - 1]) / 1e6)
    rendered_hz = float(d.values["camera_rate_hz"])
    print(f"left images {rate_hz:.1f} Hz (rendered {rendered_hz} Hz, render p50 {d.values.get('camera_render_p50_ms')} ms); "
          f"image stamp - IMU sample before it: median {np.median(gaps_ms):.2f} ms, max {max(gaps_ms):.2f} ms over "
          f"{len(gaps_ms)} frames; truth_age_ms {d.values.get('truth_age_ms')}, ground_shift_m {d.values.get('ground_shift_m')}")
    # Rendering is CPU-bound (20 Hz rated; it skips frames, never lags): the frames rendered arrive (its rate is
    # over its last 50 frames, ours over 4 s). 1-3 Hz is what two cores shared with PX4, VIO, LiDAR and six
    # other stacks gave.
    assert rate_hz >= min(1.0, 0.5 * rendered_hz) and rate_hz >= 0.5 * rendered_hz, f"{rate_hz:.1f} Hz ({d.message})"
    assert len(gaps_ms) >= 5 and max(gaps_ms) < 15.0, gaps_ms  # PX4's IMU is 100 Hz (8-12 ms apart)
    # Stereo pairs share the stamp. Images go with congestion control DROP (services/sim/qos.py: a frame
    # never blocks the vehicle's loop), so on a loaded machine one eye's frame can be dropped alone:
    # 83 of 86 paired was measured with two cores busy beside the stack
    paired = sum(m.header.stamp_ns in right for m in imgs[:-1])    # the newest one's pair may be in flight
    assert paired >= 0.9 * (len(imgs) - 1), (paired, len(imgs))
    assert d.values.get("ground_shift_m") is not None, d.values               # the pad seen on the ground


def test_px4_lidar_and_costmap_see_the_village_where_truth_puts_it(px4s):
    st = px4s
    st.ensure_landed()
    wait_until(lambda: st.latest("perception/obstacles", PointCloud, 2.0, lambda m: len(m.points.to_numpy()) > 100),
               30, "LiDAR obstacles")
    obstacles = st.latest("perception/obstacles", PointCloud).points.to_numpy()
    est = st.latest("state/vehicle", VehicleState).position_m.to_array()
    xy = obstacles[:, :2]
    near_pole = np.linalg.norm(xy - POLE, axis=1) < 0.6
    on_facade = (np.abs(xy[:, 1] - FACADE_Y_M) < 0.5) & (xy[:, 0] > FACADE_X_M[0] + 1) & (xy[:, 0] < FACADE_X_M[1] - 1)
    pole_at = xy[near_pole].mean(axis=0) if near_pole.any() else None
    facade_y = float(np.median(xy[on_facade, 1])) if on_facade.any() else None
    print(f"LiDAR on the pad (PX4 estimate {est.round(2).tolist()}, truth {st.truth.now().round(2).tolist()}): "
          f"{near_pole.sum()} points at the street light, centred {pole_at}; {on_facade.sum()} on the facade, "
          f"median y {facade_y}")
    # where the scenario puts them, within PX4's GNSS/EKF2 error about its origin (~0.3 m) and the pole's radius
    assert near_pole.sum() >= 3 and np.linalg.norm(pole_at - POLE) < 0.5, pole_at
    assert on_facade.sum() >= 20 and abs(facade_y - FACADE_Y_M) < 0.4, facade_y


def lethal_near(costmap: OccupancyGrid, xy, radius_m: float = 0.3) -> int:
    """The highest cost of the cells within radius_m of world point xy (-1: outside the window)."""
    res, ox, oy = costmap.resolution_m, costmap.origin.position.x, costmap.origin.position.y
    centres = np.stack(np.meshgrid((np.arange(costmap.width) + 0.5) * res + ox,
                                   (np.arange(costmap.height) + 0.5) * res + oy), axis=-1)   # [row, col] -> x, y
    near = np.linalg.norm(centres - np.asarray(xy), axis=-1) < radius_m
    return int(costmap.data.to_numpy()[near].max()) if near.any() else -1


def test_px4_vio_tracks_sih_truth_on_a_short_hop(px4s, tmp_path):
    st = px4s
    st.ensure_landed()
    wait_until(lambda: st.latest("state/vio_health", VioHealth, 2.0, lambda m: m.state == VioHealth.TRACKING), 40,
               "VIO TRACKING on the pad")
    mission = tmp_path / "hop.json"
    mission.write_text(json.dumps(HOP))
    with st.capture(odom=("state/visual_odometry", Odometry), truth=("fmu/out/vehicle_ground_truth", VehicleState),
                    costmap=("perception/costmap", OccupancyGrid), health=("state/vio_health", VioHealth)) as rec:
        r = subprocess.run(aero_argv() + ["mission", "fly", str(mission), "--quiet", "--timeout", "60"],
                           env=clean_env(st.endpoint), capture_output=True, text=True, timeout=80,
                           stdin=subprocess.DEVNULL)
        lag = st.diag("sim").values.get("truth_imu_lag_ms")
        wait_until(st.landed, 20, "on the ground, disarmed (PX4's land detector)")
        sim = st.diag("sim").values
        odom, truth, costmaps, health = rec.get("odom"), rec.get("truth"), rec.get("costmap"), rec.get("health")
    assert r.returncode == 0, r.stdout + r.stderr
    pole_cost = max(lethal_near(c, POLE) for c in costmaps)
    ts = np.array([m.header.stamp_ns for m in truth], float)
    tp = np.array([m.position_m.to_array() for m in truth])
    inside = [m for m in odom if ts[0] <= m.header.stamp_ns <= ts[-1]]
    est = np.array([m.pose.position.to_array() for m in inside])
    gt = np.column_stack([np.interp([m.header.stamp_ns for m in inside], ts, tp[:, k]) for k in range(3)])
    R, t = align_se3(est, gt, yaw_only=True)
    err = np.linalg.norm(est @ R.T + t - gt, axis=1)
    path_m = float(np.sum(np.linalg.norm(np.diff(tp, axis=0), axis=1)))
    ate = float(np.sqrt(np.mean(err ** 2)))
    # what explains a miss: the error along the flight, VIO's states and counters
    t_s = (np.array([m.header.stamp_ns for m in inside], float) - ts[0]) / 1e9
    err_by_2s = [round(float(err[(t_s >= a) & (t_s < a + 2)].max()), 2) for a in range(0, int(t_s[-1]) + 1, 2)
                 if ((t_s >= a) & (t_s < a + 2)).any()]
    # (s into the flight, state, where truth had the vehicle, why) at each change of VIO's state
    transitions = [(round((h.header.stamp_ns - ts[0]) / 1e9, 1), h.state_name,
                    np.round([np.interp(h.header.stamp_ns, ts, tp[:, k]) for k in range(3)], 1).tolist(), h.message)
                   for k, h in enumerate(health) if k == 0 or h.state != health[k - 1].state]
    print(f"VIO on PX4 SIH: {len(inside)} poses over {path_m:.1f} m of truth; ATE RMSE {ate:.3f} m, max "
          f"{err.max():.3f} m (yaw + translation aligned); max error per 2 s {err_by_2s}; reset counters "
          f"{sorted({m.reset_counter for m in inside})}; health states {transitions}; truth_imu_lag_ms {lag}; "
          f"rendered raised onto the ground {sim.get('below_ground')}x, by up to {sim.get('below_ground_max_m')} m; "
          f"costmap in flight: street light {pole_cost} (of {len(costmaps)}); vio {st.diag('vio').values}")
    assert path_m > 8.0 and len(inside) >= 10, (path_m, len(inside))
    # 0.39 m measured with the camera at 4 Hz on a machine shared with six other stacks; VIO not tracking
    # (a frozen or lost estimate) is metres off on this path even after the alignment
    assert ate < 0.6, ate
    assert pole_cost >= 99, pole_cost                         # lethal where the street light stands
    # Landed where PX4 puts the vehicle lower than on its pad, the cameras still see the village (the
    # sim raises a pose below the scenario's ground onto it): VIO tracks on the ground as before take-off
    wait_until(lambda: st.latest("state/vio_health", VioHealth, 2.0, lambda m: m.state == VioHealth.TRACKING), 40,
               "VIO TRACKING on the ground after the hop")
    # The truth's (the images') stamps against PX4's gyro, the median of 4 s windows: -11 to +0.9 ms measured
    # (PX4's gyro is the mean over its integration interval, stamped at its end, and its IMU integration and
    # SIH's steps beat: a few ms are PX4's own; a calm window alone can read -22 ms: a flat optimum)
    assert lag is not None and abs(float(lag)) < 20.0, lag


def test_px4_fmu_killed_the_renders_stop_said_so_and_resume_with_it(px4s):
    """No ground truth (fmu gone): sim says so (WARN) and renders nothing; the restarted fmu's truth
    brings the frames back, stamped after the last ones."""
    st = px4s
    st.ensure_landed()
    before = st.latest("sensors/camera/left/image", Image, 30.0)
    assert before is not None, "no image before the kill"
    pid = st.pid("fmu")
    assert pid is not None
    with st.capture(diag=("diagnostics/sim", DiagnosticStatus)) as rec:
        os.kill(pid, signal.SIGKILL)
        # aero up restarts fmu after 1 s: the truth is back ~2.3 s after the kill (measured), so the
        # outage is held WARN for a while after it ended; every diagnostics message is captured
        d = wait_until(lambda: next((d for d in rec.get("diag") if d.level == DiagnosticStatus.WARN
                                     and "ground truth" in d.message), None), 10, "sim: WARN, no fresh ground truth")
    print(f"fmu killed: sim says {d.message!r}")
    wait_until(lambda: st.pid("fmu") not in (None, pid), 20, "aero up restarted fmu")
    after = st.latest("sensors/camera/left/image", Image, 60.0, lambda m: m.header.stamp_ns > before.header.stamp_ns)
    assert after is not None, "no image after fmu came back"
    wait_until(lambda: st.latest_diag("sim").level == DiagnosticStatus.OK or "Hz" in st.latest_diag("sim").message, 10,
               "sim healthy again (or only slow)")
