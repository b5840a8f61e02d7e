"""`aero play`: real recordings through the unchanged live services. The MH_01 clip (real stereo
images and IMU, in motion) played into the vio service and scored live against the clip's truth
by `aero eval vio --live`, against the offline evaluation of the same clip; a real VLP-16
capture sent to the lidar_driver as the sensor sent it."""
from __future__ import annotations

import json
import socket
import subprocess

import numpy as np
import pytest

from aerotest import aero, aero_argv, clean_env, free_port, poll_until, token_alive, wait_until, zenoh_client
from aeroperception.schemas import Imu, PointCloud, VioHealth, decode
from aeroperception.services.runtime.data import shared_data_dir

DATA = shared_data_dir()
MH01 = DATA / "euroc" / "MH_01_clip" if DATA else None
VLP16 = DATA / "lidar_pcap" / "velodyne" / "vlp16_velodyne_example.pcap" if DATA else None
pytestmark = pytest.mark.skipif(MH01 is None or not (MH01 / "mav0").is_dir(), reason="../shared/data absent")


def start(argv: list[str], endpoint: str, log) -> subprocess.Popen:
    with open(log, "wb") as f:
        return subprocess.Popen(aero_argv() + argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=clean_env(endpoint))


def listening(log, proc: subprocess.Popen) -> None:
    """The driver's socket is bound (its liveliness token comes before start(): packets sent
    between the two would be lost, as a sensor's are before its driver runs)."""
    wait_until(lambda: '"listening"' in log.read_text() or proc.poll() is not None, 30, "lidar_driver listening")
    assert proc.poll() is None, log.read_text()


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def test_mh01_played_through_the_vio_service_scores_as_offline(zenoh_router, tmp_path):
    from aeroperception.services.vio.euroc import EurocDataset
    from aeroperception.tools.eval.vio import metrics, run_euroc

    offline = run_euroc(MH01)
    off = metrics([e.world_T_body for e in offline.estimates], offline.truth_T,
                  [e.pose_covariance_6x6[:3, :3] for e in offline.estimates],
                  [e.stamp_ns for e in offline.estimates], "se3", 1.0)
    noise = EurocDataset(MH01).imu_noise()
    params = [f"gyro_noise_density={noise.gyro_noise_density}", f"accel_noise_density={noise.accel_noise_density}",
              f"gyro_random_walk={noise.gyro_random_walk}", f"accel_random_walk={noise.accel_random_walk}"]
    watcher = zenoh_client(zenoh_router)
    health: list[VioHealth] = []
    watcher.declare_subscriber("state/vio_health", lambda s: health.append(decode(s.payload.to_bytes(), VioHealth)))
    vio = start(["run", "vio", "--sim-time"] + [a for p in params for a in ("--param", p)], zenoh_router,
                tmp_path / "vio.log")
    evaluator = player = None
    try:
        wait_until(lambda: token_alive(watcher, "vio") or vio.poll() is not None, 60, "vio alive")
        assert vio.poll() is None, (tmp_path / "vio.log").read_text()
        evaluator = start(["eval", "vio", "--live", "--duration", "16", "--out", str(tmp_path / "live")],
                          zenoh_router, tmp_path / "eval.log")
        wait_until(lambda: "recording" in (tmp_path / "eval.log").read_text() or evaluator.poll() is not None,
                   20, "the evaluator recording")
        player = start(["play", "euroc", str(MH01)], zenoh_router, tmp_path / "play.log")
        assert player.wait(40) == 0, (tmp_path / "play.log").read_text()
        assert evaluator.wait(30) == 0, (tmp_path / "eval.log").read_text()
        assert vio.poll() is None, (tmp_path / "vio.log").read_text()
    finally:
        for p in (player, evaluator, vio):
            if p is not None:
                stop(p)
        watcher.close()
    play_out = (tmp_path / "play.log").read_text()
    assert "240 frames (stereo)" in play_out and "played" in play_out, play_out
    live = json.loads((tmp_path / "live" / "vio_eval.json").read_text())
    print(f"MH_01 clip: live ATE {live['ate_rmse_m'] * 100:.2f} cm over {live['frames']} estimates "
          f"(offline {off['ate_rmse_m'] * 100:.2f} cm over {off['frames']}); NEES live "
          f"{live.get('nees_position_mean')} offline {off.get('nees_position_mean')}")
    assert live["ate_rmse_m"] <= 1.5 * off["ate_rmse_m"], (live, off["ate_rmse_m"])
    assert live["distance_m"] > 4.0, live                  # the whole 4.4 m path was scored
    # An honest position covariance (EKF2 weighs the odometry by it): NEES ~3, not >> 3 (8.6-13 before the
    # moving-start fix). Offline it is 2.29 every run (test_vio_euroc_motion pins <= 3); live it depends on
    # which IMU samples each frame got in time: 2.29 quiet, 3.67 in a CI run (2026-12-08). The issue's
    # live goal (<= 3 in every run) is open; this bounds what a loaded host gives.
    assert live["nees_position_mean"] <= 4.5, live
    states = [h.state for h in health]
    first = states.index(VioHealth.TRACKING)
    assert all(s == VioHealth.TRACKING for s in states[first:]), \
        [(h.state_name, h.message) for h in health[first:] if h.state != VioHealth.TRACKING]


def test_a_velodyne_capture_played_to_the_lidar_driver_comes_out_as_its_rotation(zenoh_router, tmp_path):
    port = free_port(socket.SOCK_DGRAM)
    watcher = zenoh_client(zenoh_router)
    scans: list[PointCloud] = []
    watcher.declare_subscriber("sensors/lidar/points", lambda s: scans.append(decode(s.payload.to_bytes(), PointCloud)))
    driver = start(["run", "lidar_driver", "--param", f"port={port}", "--param", "bind_address=127.0.0.1",
                    "--param", "device_ip=127.0.0.1",
                    "--param", "time_source=sensor", "--param", "min_range_m=0.1", "--param", "max_range_m=200.0"],
                   zenoh_router, tmp_path / "driver.log")
    try:
        listening(tmp_path / "driver.log", driver)
        for _ in range(3):       # a ~0.5 MB BULK scan (congestion DROP) may be dropped under load: play again
            r = aero("play", "pcap", str(VLP16), "--port", str(port), endpoint=zenoh_router, timeout_s=30)
            assert r.returncode == 0, r.stdout + r.stderr
            if poll_until(lambda: scans, 3):
                break
    finally:
        stop(driver)
        watcher.close()
    assert f"sent 84 datagrams from {VLP16} to 127.0.0.1" in r.stdout, r.stdout
    # the capture starts 35 % into a rotation (dropped); the rest is one 77 % rotation: the same
    # 21735 points the reference decoder gives (tests/integration/test_lidar_driver_service.py)
    assert scans and len(scans[0].points.to_numpy()) == 21735


def test_an_ouster_capture_played_to_the_lidar_driver_gives_its_frames_and_its_imu(zenoh_router, tmp_path):
    ouster = DATA / "lidar_pcap" / "ouster"
    port, imu_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    watcher = zenoh_client(zenoh_router)
    scans: list[PointCloud] = []
    imu: list[Imu] = []
    watcher.declare_subscriber("sensors/lidar/points", lambda s: scans.append(decode(s.payload.to_bytes(), PointCloud)))
    watcher.declare_subscriber("sensors/lidar/imu", lambda s: imu.append(decode(s.payload.to_bytes(), Imu)))
    driver = start(["run", "lidar_driver", "--param", "vendor=ouster", "--param", f"port={port}",
                    "--param", f"imu_port={imu_port}", "--param", "bind_address=127.0.0.1",
                    "--param", "device_ip=127.0.0.1", "--param", "min_range_m=0.1", "--param", "max_range_m=200.0",
                    "--param", f"metadata_path={ouster / 'OS-1-128_v2.3.0_1024x10.json'}"],
                   zenoh_router, tmp_path / "driver.log")
    try:
        listening(tmp_path / "driver.log", driver)
        r = aero("play", "pcap", str(ouster / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap"), "--port", f"7502={port}",
                 "--port", f"7503={imu_port}", "--rate", "0.25", endpoint=zenoh_router, timeout_s=30)
        assert r.returncode == 0, r.stdout + r.stderr
        poll_until(lambda: len(scans) == 3 and len(imu) == 30, 5)
        assert len(imu) == 30 and scans, f"{len(scans)} frames and {len(imu)} IMU samples, expected 3 and 30"
    finally:
        stop(driver)
        watcher.close()
    # as the unit test decodes them (a frame, ~2.6 MB on a BULK stream, may be dropped on a loaded host)
    assert {len(s.points.to_numpy()) for s in scans} <= {107646, 107350, 107529}
    acc = np.array([m.linear_acceleration_mps2.to_array() for m in imu])
    assert 9.3 < acc[:, 2].mean() < 10.3 and imu[0].header.frame_id == "lidar"


@pytest.mark.parametrize("argv, words", [
    (["play", "euroc", "/nonexistent"], "not an EuRoC/ASL folder"),
    (["play", "euroc", "MH01", "--start", "60"], "no camera frame in the window"),
    (["play", "euroc", "MH01", "--rate", "0"], "--rate 0.0: must be > 0"),
    (["play", "pcap", "/nonexistent.pcap", "--port", "9"], "No such file"),
])
def test_what_cannot_be_played_is_refused_in_one_line(argv, words):
    r = aero(*[str(MH01) if a == "MH01" else a for a in argv], timeout_s=30)
    assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r
