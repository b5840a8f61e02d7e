"""ROS 2 sensor topics into the stack through ros2bridge, from an independent ROS 2 implementation:
PyPI `zenoh-ros2-sdk` acting as a vendor's driver node on rmw_zenoh's wire format, in its own process
(nothing of ours imported there). It must see the bridge's subscriptions on liveliness before it
publishes, then sends real data: KITTI scans as PointCloud2 in a Velodyne layout (ring + float32
time) and an Ouster layout (uint32 ns t, padded to 48 bytes), EuRoC frames as Image mono8 (rows
padded) and as CompressedImage png (the file's own bytes), cam0's CameraInfo from its sensor.yaml,
and EuRoC IMU rows as Imu. Our keys must carry identical points, pixels and values, and the lidar
service's pipeline must make the same costmap of the bridged scan as of the file.
"""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest
import yaml
from ros2msgs import write_msg_files

from aerotest import aero_argv, clean_env, wait_until
from aeroperception.schemas import CameraInfo, Image, Imu, PointCloud, SchemaError, decode
from aeroperception.services.runtime.data import kitti_scans, shared_data_dir
from aeroperception.tools.harness.topics import zenoh_client

pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk is not installed (pip install .[test])")
DATA = shared_data_dir()
EUROC = DATA / "euroc" / "MH_01_clip" / "mav0" if DATA else None
if not kitti_scans() or EUROC is None or not EUROC.is_dir():
    pytest.skip("../shared/data kitti/seq00 and euroc/MH_01_clip are needed", allow_module_level=True)

ROS_TYPES = ["sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
             "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/Imu"]
SCAN = kitti_scans()[0]
FRAMES = sorted((EUROC / "cam0" / "data").glob("*.png"))[:3]
IMU_ROWS = 20
# The bridge "ros" (vehicle default) takes everything but the Ouster cloud; "ouster" (vehicle
# ouster) the same key from the Ouster layout.
BRIDGES = {
    "": "/velodyne_points=sensors/lidar/points,/cam0/image_raw=sensors/camera/left/image,"
        "/cam0/image_raw/compressed=sensors/camera/right/image,/cam0/camera_info=sensors/camera/left/info,"
        "/imu0=sensors/imu",
    "ouster": "/ouster/points=sensors/lidar/points",
}
SUBSCRIBED = ["/velodyne_points", "/ouster/points", "/cam0/image_raw", "/cam0/image_raw/compressed",
              "/cam0/camera_info", "/imu0"]


def ring_and_time(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A Velodyne-like ring (elevation in 64 rows) and sweep time (azimuth over 0.1 s) for a KITTI
    scan, which has neither: the ROS node computes the same (its copy below)."""
    el = np.degrees(np.arctan2(raw[:, 2], np.hypot(raw[:, 0], raw[:, 1])))
    ring = np.clip(np.round((el + 24.9) / 26.9 * 63), 0, 63).astype(np.uint16)
    t = ((np.arctan2(raw[:, 1], raw[:, 0]) + np.pi) / (2 * np.pi) * 0.1).astype(np.float32)
    return ring, t


# The vendor's side: only zenoh-ros2-sdk, numpy, OpenCV's PNG reader and yaml.
ROS_NODE = r'''
import json, os, sys, threading, time
os.environ["ZENOH_CONFIG_OVERRIDE"] = 'mode="client";scouting/multicast/enabled=false'
import numpy as np, yaml, cv2
from zenoh_ros2_sdk import ROS2Publisher, get_message_class, get_registry, get_topic_names_and_types
port, msgdir, args = int(sys.argv[1]), sys.argv[2], json.loads(sys.argv[3])
get_registry(msgdir)
lock = threading.Lock()
def out(**kw):
    with lock:
        sys.stdout.write(json.dumps(kw) + "\n"); sys.stdout.flush()
# wait until the bridge's subscriptions are on the graph (its MS liveliness tokens)
deadline = time.monotonic() + 20
while True:
    topics = dict(get_topic_names_and_types(router_ip="127.0.0.1", router_port=port, timeout=1.0))
    if set(args["subscribed"]) <= set(topics) or time.monotonic() > deadline:
        break
out(kind="topics", topics=topics)
pub = {t: ROS2Publisher(t, typ, router_ip="127.0.0.1", router_port=port) for t, typ in [
    ("/velodyne_points", "sensor_msgs/msg/PointCloud2"), ("/ouster/points", "sensor_msgs/msg/PointCloud2"),
    ("/cam0/image_raw", "sensor_msgs/msg/Image"), ("/cam0/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
    ("/cam0/camera_info", "sensor_msgs/msg/CameraInfo"), ("/imu0", "sensor_msgs/msg/Imu")]}
# the message classes once a publisher has opened the SDK's session on our router
M = {n: get_message_class(n) for n in ["std_msgs/msg/Header", "builtin_interfaces/msg/Time",
     "sensor_msgs/msg/PointField", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Vector3",
     "sensor_msgs/msg/RegionOfInterest"]}
def header(stamp_ns, frame):
    return M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
                                    frame_id=frame)
raw = np.fromfile(args["scan"], np.float32).reshape(-1, 4)
n = len(raw)
el = np.degrees(np.arctan2(raw[:, 2], np.hypot(raw[:, 0], raw[:, 1])))
ring = np.clip(np.round((el + 24.9) / 26.9 * 63), 0, 63).astype(np.uint16)
t = ((np.arctan2(raw[:, 1], raw[:, 0]) + np.pi) / (2 * np.pi) * 0.1).astype(np.float32)
def cloud(names, formats, offsets, step, values):
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    a = np.zeros(n, dt)
    for k, v in zip(names, values):
        a[k] = v
    codes = {"<f4": 7, "<u2": 4, "<u4": 6, "<f8": 8, "u1": 2}
    return dict(height=1, width=n, is_bigendian=False, point_step=step, row_step=step * n, is_dense=True,
                data=a.view(np.uint8), fields=[M["sensor_msgs/msg/PointField"](name=k, offset=o, datatype=codes[f], count=1)
                                               for k, f, o in zip(names, formats, offsets)])
x, y, z, i = raw[:, 0], raw[:, 1], raw[:, 2], raw[:, 3]
velodyne = cloud(["x", "y", "z", "intensity", "ring", "time"], ["<f4"] * 4 + ["<u2", "<f4"], [0, 4, 8, 12, 16, 18], 22,
                 [x, y, z, i, ring, t])
t_ns = np.round(t.astype(np.float64) * 1e9).astype(np.uint32)
ouster = cloud(["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
               ["<f4"] * 4 + ["<u4", "<u2", "<u2", "<u2", "<u4"], [0, 4, 8, 16, 20, 24, 26, 28, 32], 48,
               [x, y, z, i, t_ns, ring * 2, ring, ring * 3, t_ns])
cal = yaml.safe_load(open(args["cam_yaml"]))
fu, fv, cu, cv = cal["intrinsics"]
K = [fu, 0.0, cu, 0.0, fv, cv, 0.0, 0.0, 1.0]
info = dict(height=cal["resolution"][1], width=cal["resolution"][0], distortion_model="plumb_bob",
            d=np.array(cal["distortion_coefficients"] + [0.0]), k=np.array(K), r=np.eye(3).reshape(-1),
            p=np.array([fu, 0.0, cu, 0.0, 0.0, fv, cv, 0.0, 0.0, 0.0, 1.0, 0.0]), binning_x=0, binning_y=0,
            roi=M["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
imu_rows = np.loadtxt(args["imu_csv"], delimiter=",", skiprows=1, max_rows=args["imu_rows"], dtype=np.float64)
imu_stamps = [int(s) for s in np.loadtxt(args["imu_csv"], delimiter=",", skiprows=1, max_rows=args["imu_rows"], usecols=0, dtype=np.int64)]
V, Q = M["geometry_msgs/msg/Vector3"], M["geometry_msgs/msg/Quaternion"]
out(kind="ready", points=n)
for line in sys.stdin:          # one line: publish everything once; EOF: quit
    stamp = args["scan_stamp_ns"]
    pub["/velodyne_points"].publish(header=header(stamp, "velodyne"), **velodyne)
    pub["/ouster/points"].publish(header=header(stamp, "os_lidar"), **ouster)
    for path, stamp_ns in args["frames"]:
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        step = img.shape[1] + 16                     # rows padded, as a driver aligning them does
        padded = np.zeros((img.shape[0], step), np.uint8)
        padded[:, :img.shape[1]] = img
        pub["/cam0/image_raw"].publish(header=header(stamp_ns, "cam0"), height=img.shape[0], width=img.shape[1],
                                       encoding="mono8", is_bigendian=0, step=step, data=padded.reshape(-1))
        pub["/cam0/image_raw/compressed"].publish(header=header(stamp_ns, "cam0"), format="mono8; png compressed mono8",
                                                  data=np.fromfile(path, np.uint8))
    pub["/cam0/camera_info"].publish(header=header(args["frames"][0][1], "cam0"), **info)
    for s, r in zip(imu_stamps, imu_rows):
        pub["/imu0"].publish(header=header(s, "imu4"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                             orientation_covariance=np.array([-1.0] + [0.0] * 8),
                             angular_velocity=V(x=r[1], y=r[2], z=r[3]), angular_velocity_covariance=np.zeros(9),
                             linear_acceleration=V(x=r[4], y=r[5], z=r[6]), linear_acceleration_covariance=np.zeros(9))
    out(kind="published")
'''


class Collected:
    """Every message on our keys (any vehicle prefix), decoded, by key."""

    KEYS = {"sensors/lidar/points": PointCloud, "sensors/camera/left/image": Image,
            "sensors/camera/right/image": Image, "sensors/camera/left/info": CameraInfo, "sensors/imu": Imu}

    def __init__(self, session):
        self.by_key: dict[str, list] = {}
        self.lock = threading.Lock()
        self.subs = [session.declare_subscriber(k, self._on) for k in (*self.KEYS, *(f"*/{k}" for k in self.KEYS))]

    def _on(self, sample) -> None:
        key = str(sample.key_expr)
        cls = next(c for k, c in self.KEYS.items() if key.endswith(k))
        try:
            msg = decode(sample.payload.to_bytes(), cls)
        except SchemaError:
            return
        with self.lock:
            self.by_key.setdefault(key, []).append(msg)

    def of(self, key: str) -> list:
        with self.lock:
            return list(self.by_key.get(key, []))


def costmap(points: np.ndarray) -> np.ndarray:
    """The lidar service's pipeline and costmap on one scan, the sensor levelled at the origin."""
    from aeroperception.services.lidar import contract
    from aeroperception.services.lidar.config import LidarConfig
    from aeroperception.services.lidar.costmap import RollingCostmap
    from aeroperception.services.lidar.pipeline import ObstaclePipeline
    from aeroperception.services.runtime.config import build

    cfg = build(LidarConfig, contract.PARAMS)
    res = ObstaclePipeline(cfg.pipeline, seed=0).process(points, np.eye(3), 0.0)
    cm = RollingCostmap(cfg.costmap)
    cm.recenter(0.0, 0.0)
    cm.update((0.0, 0.0), res.obstacles, res.downsampled, res.ground)
    return cm.inflated()


def test_ros2_sensor_topics_reach_our_keys_identical_and_make_the_same_costmap(zenoh_router, tmp_path):
    port = int(zenoh_router.rsplit(":", 1)[1])
    write_msg_files(tmp_path / "msgs", ROS_TYPES)
    logs, bridges = [], []
    for vehicle, inputs in BRIDGES.items():
        log = open(tmp_path / f"ros2bridge{vehicle}.log", "w")
        logs.append(log)
        argv = aero_argv() + ["run", "ros2bridge", "--param", "topics=", "--param", "goal_topic=",
                              "--param", f"inputs={inputs}"]
        if vehicle:
            argv += ["--vehicle", vehicle]
        else:
            argv += ["--param", "left_mount_x_m=0.1", "--param", "left_mount_pitch_deg=30"]
        bridges.append(subprocess.Popen(argv, env=clean_env(zenoh_router), stdout=log, stderr=subprocess.STDOUT))
    session = zenoh_client(zenoh_router)
    got = Collected(session)
    frames = [(str(p), int(p.stem)) for p in FRAMES]
    scan_stamp_ns = 1_317_000_000_123_456_789
    args = dict(subscribed=SUBSCRIBED, scan=str(SCAN), scan_stamp_ns=scan_stamp_ns, frames=frames,
                cam_yaml=str(EUROC / "cam0" / "sensor.yaml"), imu_csv=str(EUROC / "imu0" / "data.csv"),
                imu_rows=IMU_ROWS)
    ros = subprocess.Popen([sys.executable, "-u", "-c", ROS_NODE, str(port), str(tmp_path / "msgs"), json.dumps(args)],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, errors="replace")
    lines: list[dict] = []
    err: list[str] = []
    threading.Thread(target=lambda: [lines.append(json.loads(ln)) for ln in ros.stdout if ln.startswith("{")],
                     daemon=True).start()
    threading.Thread(target=lambda: err.extend(ros.stderr), daemon=True).start()
    keys = ["sensors/lidar/points", "ouster/sensors/lidar/points", "sensors/camera/left/image",
            "sensors/camera/right/image", "sensors/camera/left/info", "sensors/imu"]
    try:
        wait_until(lambda: any(d["kind"] == "ready" for d in lines) or ros.poll() is not None, 60, "the ROS node")
        assert any(d["kind"] == "ready" for d in lines), "".join(err)[-3000:]
        # The bridge's subscriptions are on the ROS graph (liveliness MS tokens), with their types.
        topics = next(d["topics"] for d in lines if d["kind"] == "topics")
        assert topics.get("/velodyne_points") == ["sensor_msgs/msg/PointCloud2"], topics
        assert topics.get("/cam0/image_raw/compressed") == ["sensor_msgs/msg/CompressedImage"], topics
        for t in SUBSCRIBED:
            assert t in topics, (t, topics)

        def all_arrived():
            ros.stdin.write("go\n")
            ros.stdin.flush()
            time.sleep(1.0)
            return all(got.of(k) for k in keys) and len(got.of("sensors/imu")) >= IMU_ROWS \
                and len(got.of("sensors/camera/left/image")) >= len(FRAMES)
        wait_until(all_arrived, 60, "every bridged sensor key", interval_s=0.5)

        raw = np.fromfile(SCAN, np.float32).reshape(-1, 4)
        ring, t = ring_and_time(raw)
        for key in ("sensors/lidar/points", "ouster/sensors/lidar/points"):
            pc = got.of(key)[0]
            assert (pc.header.stamp_ns, pc.header.frame_id) == (scan_stamp_ns, "velodyne" if key[0] == "s" else "os_lidar")
            assert np.array_equal(pc.points.to_numpy(), raw[:, :3]), key
            assert np.array_equal(pc.intensity.to_numpy(), raw[:, 3]) and np.array_equal(pc.ring.to_numpy(), ring), key
        assert np.array_equal(got.of("sensors/lidar/points")[0].time_offset_s.to_numpy(), t)
        t_ns = np.round(t.astype(np.float64) * 1e9).astype(np.uint32)
        assert np.array_equal(got.of("ouster/sensors/lidar/points")[0].time_offset_s.to_numpy(),
                              (t_ns * 1e-9).astype(np.float32))
        # "a costmap from the bridged scan equals the one from the direct path"
        direct = costmap(raw[:, :3].copy())
        assert (direct == 100).sum() > 100                       # the scan's cars and walls are in it
        for key in ("sensors/lidar/points", "ouster/sensors/lidar/points"):
            assert np.array_equal(costmap(np.array(got.of(key)[0].points.to_numpy())), direct), key

        for side in ("left", "right"):        # raw mono8 with padded rows; the PNG file's own bytes
            images = {m.header.stamp_ns: m for m in got.of(f"sensors/camera/{side}/image")}
            for path, stamp_ns in frames:
                m = images[stamp_ns]
                assert m.encoding == "mono8" and m.header.frame_id == "cam0"
                assert np.array_equal(m.to_numpy(), cv2.imread(path, cv2.IMREAD_UNCHANGED)), (side, path)

        cal = yaml.safe_load((EUROC / "cam0" / "sensor.yaml").read_text())
        info = got.of("sensors/camera/left/info")[0]
        fu, fv, cu, cv = cal["intrinsics"]
        assert np.array_equal(info.K.to_numpy(), [[fu, 0, cu], [0, fv, cv], [0, 0, 1]])
        assert np.array_equal(info.D.to_numpy(), cal["distortion_coefficients"] + [0.0])
        assert (info.width, info.height) == tuple(cal["resolution"]) and info.header.stamp_ns == frames[0][1]
        assert info.T_body_camera.position.x == pytest.approx(0.1)     # from left_mount_x_m

        rows = np.loadtxt(EUROC / "imu0" / "data.csv", delimiter=",", skiprows=1, max_rows=IMU_ROWS)
        stamps = np.loadtxt(EUROC / "imu0" / "data.csv", delimiter=",", skiprows=1, max_rows=IMU_ROWS, usecols=0, dtype=np.int64)
        imus = {m.header.stamp_ns: m for m in got.of("sensors/imu")}
        for s, r in zip(stamps, rows):
            m = imus[int(s)]
            w, a = m.angular_velocity_radps, m.linear_acceleration_mps2
            assert (w.x, w.y, w.z, a.x, a.y, a.z) == tuple(r[1:7]) and not m.has_orientation

        # What the bridge reports: samples received, none refused, the conversion time per key.
        from aerotest import wait_for_message
        from aeroperception.schemas import DiagnosticStatus
        d = wait_for_message(session, "diagnostics/ros2bridge", DiagnosticStatus,
                             lambda d: int(d.values.get("received", 0)) > 0, timeout_s=5)
        assert int(d.values["input_errors"]) == 0, d.values
        print(f"\nbridge conversion ms (last sample): "
              f"{ {k: v for k, v in d.values.items() if k.startswith('convert_ms')} }")
        assert all(b.poll() is None for b in bridges)
    finally:
        if ros.poll() is None:
            ros.stdin.close()
            try:
                ros.wait(5)
            except subprocess.TimeoutExpired:
                ros.kill()
        for b in bridges:
            b.terminate()
            b.wait(8)
        for log in logs:
            log.close()
        for s in got.subs:
            s.undeclare()
        session.close()
    assert "Traceback" not in "".join(err), "".join(err)[-3000:]


def test_bridge_refuses_an_input_it_cannot_feed_at_start(zenoh_router, tmp_path):
    r = subprocess.run(aero_argv() + ["run", "ros2bridge", "--param", "inputs=/cam=sensors/camera/down/image"],
                       env=clean_env(zenoh_router), capture_output=True, text=True, timeout=30)
    assert r.returncode != 0 and "sensors/camera/down/image cannot be fed from ROS" in r.stderr + r.stdout
