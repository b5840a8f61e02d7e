"""The vio service process over a real Zenoh router, fed the real EuRoC start (stereo mono8
752x480 at 20 Hz with its radtan calibration as CameraInfo, the 200 Hz IMU) by a small publisher
in this test: state/visual_odometry arrives at camera rate in odom/base_link with a 6x6 covariance
and the vehicle's stillness, state/vio_health says TRACKING, garbage on its inputs is counted
and survived, and vio/srv/reset restarts it from a given pose (a bad pose refused). Skipped (not failed) only when the shared data folder is absent.
Also: an unavailable strategy fails at start naming what exists, and (slow) the service on the
simulator's own sensors (rgb8 stereo, CameraInfo queryable, sim IMU) tracks the still vehicle."""
from __future__ import annotations

import json
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
import zenoh

from aerotest import aero_argv, clean_env, free_udp_port, wait_until, zenoh_client

from aeroperception.schemas import (
    CameraInfo, DiagnosticStatus, Header, Image, Imu, Odometry, ParamSet, ParamSetReply, Pose, Reply, SchemaError,
    Vector3, VioHealth, VioResetRequest, decode,
)
from aeroperception.services.vio.euroc import EurocDataset, default_euroc_dir

EUROC = default_euroc_dir()
pytestmark = pytest.mark.timeout(120)
needs_euroc = pytest.mark.skipif(EUROC is None, reason="EuRoC data not found: expected ../shared/data/euroc/"
                                 "V1_01_easy_start next to the checkout (or set AERO_DATA_DIR)")


class Collector:
    def __init__(self, session: zenoh.Session, key: str, cls):
        self.msgs, self.lock = [], threading.Lock()
        self.cls = cls
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), self.cls)
        except SchemaError:
            return
        with self.lock:
            self.msgs.append(msg)

    def all(self):
        with self.lock:
            return list(self.msgs)


def _euroc_params(ds: EurocDataset) -> list[str]:
    n = ds.imu_noise()
    out = []
    for name in ("gyro_noise_density", "accel_noise_density", "gyro_random_walk", "accel_random_walk"):
        out += ["--param", f"{name}={getattr(n, name)}"]
    return out


def _publish_euroc(node, ds: EurocDataset, stop: threading.Event, garbage_at: int, on_frame=None,
                   black: range = range(0)) -> None:
    """Like a camera driver + IMU: IMU samples up to each frame's stamp, then the stereo pair, at
    20 Hz wall time; the calibration at 1 Hz and as a queryable. Frames in `black` are black (a
    covered lens: no visual fix)."""
    left_info, right_info = ds.camera_infos()
    right_info.header.frame_id = "camera_right_optical"
    pubs = {k: node.publisher(k, cls) for k, cls in (
        ("sensors/camera/left/image", Image), ("sensors/camera/right/image", Image),
        ("sensors/camera/left/info", CameraInfo), ("sensors/camera/right/info", CameraInfo), ("sensors/imu", Imu))}
    node.serve("sensors/camera/left/info", None, CameraInfo, lambda _r: left_info)
    node.serve("sensors/camera/right/info", None, CameraInfo, lambda _r: right_info)
    imu = ds.imu_array
    j, last_info = 0, 0.0
    t_start = time.monotonic()
    for k, t in enumerate(ds.frame_stamps_ns):
        if stop.is_set():
            return
        if time.monotonic() - last_info > 1.0:
            pubs["sensors/camera/left/info"].publish(left_info)
            pubs["sensors/camera/right/info"].publish(right_info)
            last_info = time.monotonic()
        while j < len(imu) and imu[j, 0] <= t:
            pubs["sensors/imu"].publish(Imu(header=Header(stamp_ns=int(imu[j, 0]), frame_id="base_link"),
                                            angular_velocity_radps=Vector3.from_array(imu[j, 1:4]),
                                            linear_acceleration_mps2=Vector3.from_array(imu[j, 4:7])))
            j += 1
        if on_frame is not None:
            on_frame(k)
        if k == garbage_at:
            node.session.put("sensors/imu", b"\x93not an imu")           # undecodable
            node.session.put("sensors/camera/left/image", b"\x01\x02")
        left, right = ds.load_pair(int(t))
        if k in black:
            left, right = np.zeros_like(left), np.zeros_like(right)
        pubs["sensors/camera/left/image"].publish(Image.from_numpy(left, "mono8", Header(stamp_ns=int(t), frame_id="camera_left_optical")))
        pubs["sensors/camera/right/image"].publish(Image.from_numpy(right, "mono8", Header(stamp_ns=int(t), frame_id="camera_right_optical")))
        delay = t_start + (k + 1) * 0.05 - time.monotonic()
        if delay > 0:
            time.sleep(delay)


@needs_euroc
def test_vio_service_tracks_the_real_euroc_start_over_zenoh(zenoh_router, make_node, tmp_path):
    ds = EurocDataset(EUROC)
    watcher = zenoh_client(zenoh_router)
    odom = Collector(watcher, "state/visual_odometry", Odometry)
    health = Collector(watcher, "state/vio_health", VioHealth)
    diags = Collector(watcher, "diagnostics/vio", DiagnosticStatus)
    log = tmp_path / "vio.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen(aero_argv() + ["run", "vio", *_euroc_params(ds)], stdout=subprocess.DEVNULL,
                                stderr=f, stdin=subprocess.DEVNULL, env=clean_env(zenoh_router))
    stop = threading.Event()
    try:
        wait_until(lambda: proc.poll() is not None or any(
            r.ok is not None for r in watcher.liveliness().get("aero/alive/default/vio", timeout=1.0)),
            30, "vio's liveliness token")
        assert proc.poll() is None, log.read_text()
        time.sleep(0.5)   # subscriptions propagate through the router
        node = make_node("euroc_player")
        reset_at, replies = 70, []

        def reset(k: int) -> None:   # warm start over vio/srv/reset: a bad pose refused, then a good one
            if k == reset_at:
                replies.append(node.call("vio/srv/reset", VioResetRequest(pose=Pose(position=Vector3(x=float("inf")))), Reply))
                replies.append(node.call("vio/srv/reset", VioResetRequest(pose=Pose(position=Vector3(x=10.0, y=-2.0, z=3.0))), Reply))

        strategy_set = []

        def on_frame(k: int) -> None:
            reset(k)
            if k == 20:   # strategy is chosen at start: refused live, saying so
                strategy_set.append(node.call("config/vio/@set", ParamSet(name="strategy", value="klt_mono"),
                                              ParamSetReply))

        # 14 black frames (> lost_after_frames 10): DEGRADED, then LOST, then back to TRACKING.
        _publish_euroc(node, ds, stop, garbage_at=40, on_frame=on_frame, black=range(44, 58))
        wait_until(lambda: len(odom.all()) >= 40, 10, "40 odometry messages")

        msgs = odom.all()
        assert len(msgs) >= 60, f"only {len(msgs)} odometry messages for 95 frames\n{log.read_text()[-3000:]}"
        m = msgs[-1]
        assert m.header.frame_id == "odom" and m.child_frame_id == "base_link"
        stamps = [x.header.stamp_ns for x in msgs]
        assert stamps == sorted(stamps) and set(stamps) <= set(int(t) for t in ds.frame_stamps_ns)
        t_reset = int(ds.frame_stamps_ns[reset_at])
        p = np.array([x.pose.position.to_array() for x in msgs if x.header.stamp_ns < t_reset])
        assert np.linalg.norm(p - p[0], axis=1).max() < 0.05          # the vehicle is still
        assert [r.success for r in replies] == [False, True] and "finite" in replies[0].message, replies
        # restarted from the requested pose (odom), still there
        assert np.allclose(m.pose.position.to_array(), [10.0, -2.0, 3.0], atol=0.05), m.pose.position
        cov = m.pose_covariance.to_numpy()
        assert cov.shape == (6, 6) and np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0)
        assert np.sqrt(cov[:3, :3].diagonal()).max() < 0.05
        wait_until(lambda: any(h.state == VioHealth.TRACKING for h in health.all()), 5, "health TRACKING")
        h = [x for x in health.all() if x.state == VioHealth.TRACKING][-1]
        assert h.strategy == "klt_stereo" and h.tracked_features >= 40 and h.bias_norm > 0
        (refused,) = strategy_set
        assert not refused.success and "strategy is read at start only" in refused.message and refused.value == "klt_stereo"
        assert health.all()[-1].state == VioHealth.TRACKING
        d = wait_until(lambda: [x for x in diags.all() if int(x.values.get("invalid_msgs", 0)) >= 2], 5,
                       "diagnostics counting the garbage")[-1]
        assert int(d.values["keyframes"]) >= 1 and float(d.values["total_ms_p50"]) > 0
        assert proc.poll() is None, "garbage input must not crash the service"
    finally:
        stop.set()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                code = proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
                code = None
            assert code == 0, log.read_text()[-3000:]
        watcher.close()
    records = [json.loads(ln) for ln in log.read_text().splitlines() if ln.startswith("{")]
    events = [r["event"] for r in records]
    assert "vio_started" in events and "vio_reset_requested" in events and events[-1] == "stopped"
    # State changes are logged at the level they deserve: losing the fix warns, LOST is an error,
    # initialising and recovering are info.
    changes = [(r["state"], r["level"]) for r in records if r["event"] == "vio_state"]
    assert ("DEGRADED", "warn") in changes and ("LOST", "error") in changes, changes
    assert changes[changes.index(("LOST", "error")) + 1] == ("TRACKING", "info"), changes
    assert {lvl for st_, lvl in changes if st_ in ("INIT", "TRACKING")} == {"info"}, changes


def _start_vio(endpoint: str, log, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(aero_argv() + ["run", "vio", *extra], stdout=subprocess.DEVNULL, stderr=log,
                            stdin=subprocess.DEVNULL, env=clean_env(endpoint))


def _stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
            return None
    return proc.returncode


def test_unavailable_strategy_fails_at_start_naming_what_exists(zenoh_router, tmp_path):
    log = tmp_path / "vio.log"
    with open(log, "wb") as f:
        proc = _start_vio(zenoh_router, f, "--param", "strategy=okvis2")
    try:
        code = proc.wait(30)
    finally:
        _stop(proc)
    assert code == 1
    fatal = [json.loads(ln) for ln in log.read_text().splitlines() if ln.startswith("{") and '"fatal"' in ln]
    assert fatal and "okvis2" in fatal[0]["error"] and "klt_stereo, klt_mono" in fatal[0]["error"]


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_vio_service_tracks_on_the_simulators_sensors(stack, tmp_path):
    """`aero up --only sim --scenario village` + `aero run vio`: the still vehicle on the ground;
    the VIO initialises from the sim's IMU, reads the calibration from the sim, stays TRACKING and
    its pose stays with the truth (the vehicle does not move)."""
    st = stack(["sim"], extra_args=["--scenario", "village",
                                    "--arg", f"sim:--target=127.0.0.1:{free_udp_port()}",
                                    "--arg", f"sim:--bind=127.0.0.1:{free_udp_port()}"], timeout_s=60)
    log = tmp_path / "vio.log"
    with open(log, "wb") as f:
        proc = _start_vio(st.endpoint, f)
    odom = Collector(st.session, "state/visual_odometry", Odometry)
    health = Collector(st.session, "state/vio_health", VioHealth)
    try:
        wait_until(lambda: len(odom.all()) >= 60 or proc.poll() is not None, 60, "60 odometry messages")
        assert proc.poll() is None, log.read_text()[-3000:]
        wait_until(lambda: health.all() and health.all()[-1].state == VioHealth.TRACKING, 10, "TRACKING")
        msgs = odom.all()
        p = np.array([m.pose.position.to_array() for m in msgs])
        assert np.linalg.norm(p - p[0], axis=1).max() < 0.05
        q = msgs[-1].pose.orientation
        assert abs(q.to_euler()[0]) < 0.02 and abs(q.to_euler()[1]) < 0.02   # level on the ground
        assert health.all()[-1].tracked_features >= 40
    finally:
        assert _stop(proc) == 0, log.read_text()[-3000:]
