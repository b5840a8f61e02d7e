"""ros2bridge against an independent ROS 2 implementation: PyPI `zenoh-ros2-sdk` acting as a ROS 2
node on rmw_zenoh's wire format, in its own process. It must list our topics (liveliness), compute
the same keys from the message definitions (its own RIHS01 hashing), decode our CDR, and its
PoseStamped on /aero/goal must reach the mission's goto action through the bridge.

This machine has no network access to the SDK's default source of .msg files (it clones
ros2/common_interfaces from GitHub), so the test writes the definitions it needs from rosbags'
ROS 2 Jazzy store into a folder the SDK reads first; the SDK parses them and hashes them itself.
"""
from __future__ import annotations

import collections
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ros2msgs import write_msg_files

from aerotest import aero_argv, clean_env, poll_until, wait_for_message, wait_until
from aeroperception.schemas import (
    Detection2D, Detection2DArray, DiagnosticStatus, GoalReply, GoalStatus, GoToPositionGoal, Header, Image, Imu, NDArray,
    Odometry, PointCloud, Quaternion, Vector3, VehicleState,
)

pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk is not installed (pip install .[test])")

TOPICS = "state/vehicle,state/visual_odometry,sensors/imu,sensors/camera/left/image,sensors/lidar/points,perception/detections"
ROS_TYPES = ["nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu", "sensor_msgs/msg/Image", "sensor_msgs/msg/PointCloud2",
             "vision_msgs/msg/Detection2DArray", "geometry_msgs/msg/PoseStamped"]
# What `ros2 topic list` must show of the bridge: its publications and, last declared, its subscription.
LISTED = {"/aero/odom": "nav_msgs/msg/Odometry", "/aero/camera/left/image_raw": "sensor_msgs/msg/Image",
          "/aero/lidar/points": "sensor_msgs/msg/PointCloud2", "/aero/detections": "vision_msgs/msg/Detection2DArray",
          "/aero/vio/odom": "nav_msgs/msg/Odometry", "/aero/goal": "geometry_msgs/msg/PoseStamped"}

# The ROS 2 side: only zenoh-ros2-sdk (and its rosbags) -- nothing of ours is imported.
ROS_NODE = r'''
import json, os, sys, threading, time
os.environ["ZENOH_CONFIG_OVERRIDE"] = 'mode="client";scouting/multicast/enabled=false'
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_message_class, get_registry, get_topic_names_and_types
port, msgdir, expected = int(sys.argv[1]), sys.argv[2], set(json.loads(sys.argv[3]))
get_registry(msgdir)
_out_lock = threading.Lock()
def out(**kw):
    # one write per report under a lock: print() writes the text and its newline separately, so a
    # subscriber callback's report could land between them and spoil both lines
    with _out_lock:
        sys.stdout.write(json.dumps(kw) + "\n")
        sys.stdout.flush()
deadline = time.monotonic() + 15
while True:
    topics = dict(get_topic_names_and_types(router_ip="127.0.0.1", router_port=port, timeout=1.0))
    # Each token is its own reply to a liveliness query bounded at 1 s: a loaded machine can return
    # part of them (seen once: /aero/goal, declared last, listed but not /aero/detections).
    if expected <= set(topics) or time.monotonic() > deadline:
        break
out(kind="topics", topics=topics)
def sub(topic, typ, summary):
    s = ROS2Subscriber(topic, typ, lambda m: out(kind="msg", topic=topic, **summary(m)),
                       router_ip="127.0.0.1", router_port=port)
    out(kind="key", topic=topic, key=s.keyexpr)
sub("/aero/odom", "nav_msgs/msg/Odometry", lambda m: dict(
    frame=m.header.frame_id, child=m.child_frame_id, p=[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z],
    q=[m.pose.pose.orientation.w, m.pose.pose.orientation.z], v=[m.twist.twist.linear.x, m.twist.twist.linear.y],
    stamp=[m.header.stamp.sec, m.header.stamp.nanosec]))
sub("/aero/imu", "sensor_msgs/msg/Imu", lambda m: dict(acc_z=m.linear_acceleration.z, gyro_x=m.angular_velocity.x,
                                                       ocov0=float(m.orientation_covariance[0])))
sub("/aero/camera/left/image_raw", "sensor_msgs/msg/Image", lambda m: dict(
    h=m.height, w=m.width, enc=m.encoding, step=m.step, px=int(m.data[m.step + 3 * 2 + 1])))
sub("/aero/lidar/points", "sensor_msgs/msg/PointCloud2", lambda m: dict(
    n=m.width, fields=[f.name for f in m.fields], point_step=m.point_step,
    first=[float(v) for v in m.data[:m.point_step].view("<f4")]))
sub("/aero/detections", "vision_msgs/msg/Detection2DArray", lambda m: dict(
    n=len(m.detections), cls=m.detections[0].results[0].hypothesis.class_id, score=m.detections[0].results[0].hypothesis.score,
    cx=m.detections[0].bbox.center.position.x, sx=m.detections[0].bbox.size_x))
pub = ROS2Publisher("/aero/goal", "geometry_msgs/msg/PoseStamped", router_ip="127.0.0.1", router_port=port)
out(kind="key", topic="/aero/goal", key=pub.keyexpr)
T = {n: get_message_class(n) for n in ["std_msgs/msg/Header", "builtin_interfaces/msg/Time", "geometry_msgs/msg/Pose",
                                       "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion"]}
out(kind="ready")
for line in sys.stdin:          # "goal" -> publish one goal; EOF -> quit
    pub.publish(header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="map"),
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=4.0, y=-3.0, z=6.0),
                                                 orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.7071068, w=0.7071068)))
    out(kind="published")
'''


class RosNode:
    """The SDK script as a subprocess; its JSON lines collected."""

    def __init__(self, port: int, msgdir: Path):
        self.proc = subprocess.Popen([sys.executable, "-u", "-c", ROS_NODE, str(port), str(msgdir), json.dumps(list(LISTED))],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     errors="replace")   # a stray byte must not end the reader
        self.lines: list[dict] = []
        self.other: collections.deque[str] = collections.deque(maxlen=20)   # stdout lines not a report
        self.err: collections.deque[str] = collections.deque(maxlen=200)
        import threading
        threading.Thread(target=self._read, daemon=True).start()
        # stderr drained too: a node logging under load (zenoh's warnings) would otherwise fill the
        # pipe's 64 KB and block in a write, its publishing stalled
        self._err_reader = threading.Thread(target=lambda: self.err.extend(self.proc.stderr), daemon=True)
        self._err_reader.start()

    def _read(self):
        for line in self.proc.stdout:
            try:
                d = json.loads(line)
            except ValueError:          # a library's own print: not one of the node's reports
                self.other.append(line[:300])
                continue
            if isinstance(d, dict) and "kind" in d:
                self.lines.append(d)

    def of(self, kind: str, topic: str | None = None) -> list[dict]:
        return [d for d in list(self.lines) if d["kind"] == kind and (topic is None or d.get("topic") == topic)]

    def close(self) -> str:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._err_reader.join(2.0)
        return "".join(self.err)[-3000:]


def test_ros2_node_sees_decodes_and_commands_through_the_bridge(zenoh_router, make_node, tmp_path):
    port = int(zenoh_router.rsplit(":", 1)[1])
    write_msg_files(tmp_path / "msgs", ROS_TYPES)
    log = open(tmp_path / "ros2bridge.log", "w")
    bridge = subprocess.Popen(aero_argv() + ["run", "ros2bridge", "--param", f"topics={TOPICS}",
                                             "--param", "max_rate_hz=50"],
                              env=clean_env(zenoh_router), stdout=log, stderr=subprocess.STDOUT)
    stack = make_node("fmu")
    goals: list[GoToPositionGoal] = []

    def accept(goal: GoToPositionGoal) -> GoalReply:  # the mission's goto action, as a stand-in
        goals.append(goal)
        return GoalReply(success=True, message="accepted", goal_id="g1", status=GoalStatus.ACCEPTED)

    stack.serve("mission/action/goto/goal", GoToPositionGoal, GoalReply, accept)
    pubs = {k: stack.publisher(k, c) for k, c in [("state/vehicle", VehicleState), ("sensors/imu", Imu),
                                                   ("sensors/camera/left/image", Image),
                                                   ("sensors/lidar/points", PointCloud),
                                                   ("perception/detections", Detection2DArray)]}
    yaw90 = Quaternion(w=0.7071068, x=0.0, y=0.0, z=0.7071068)
    img = np.zeros((4, 6, 3), np.uint8)
    img[1, 2, 1] = 200
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.float32)
    stamp = 1_700_000_000_250_000_000
    samples = {
        "state/vehicle": VehicleState(header=Header(stamp_ns=stamp, frame_id="map"), position_m=Vector3(x=1.0, y=2.0, z=3.0),
                                      orientation=yaw90, velocity_mps=Vector3(x=0.0, y=2.0, z=0.0)),
        "sensors/imu": Imu(linear_acceleration_mps2=Vector3(z=9.81), angular_velocity_radps=Vector3(x=0.1)),
        "sensors/camera/left/image": Image(height=4, width=6, encoding="rgb8", data=NDArray.from_numpy(img)),
        "sensors/lidar/points": PointCloud(points=NDArray.from_numpy(pts), intensity=NDArray.from_numpy(np.array([0.5, 0.7], np.float32))),
        "perception/detections": Detection2DArray(detections=[Detection2D(center_x_px=320.0, center_y_px=200.0, size_x_px=40.0,
                                                                          size_y_px=30.0, class_id=0, class_name="person", score=0.9)]),
    }
    ros = RosNode(port, tmp_path / "msgs")
    try:
        wait_until(lambda: ros.of("ready") or ros.proc.poll() is not None, 40, "the ROS node to start")
        assert ros.of("ready"), ros.close()
        topics = ros.of("topics")[0]["topics"]
        for topic, ros_type in LISTED.items():
            assert topics.get(topic) == [ros_type], (topic, topics)
        # Published until every topic has been decoded at least once (bounded).
        want = ["/aero/odom", "/aero/imu", "/aero/camera/left/image_raw", "/aero/lidar/points", "/aero/detections"]

        def all_seen():
            for k, m in samples.items():
                pubs[k].publish(m)
            return all(ros.of("msg", t) for t in want)
        wait_until(all_seen, 15, "every bridged topic decoded by the ROS node", interval_s=0.1)

        odom = ros.of("msg", "/aero/odom")[0]
        assert odom["frame"] == "map" and odom["child"] == "base_link" and odom["p"] == [1.0, 2.0, 3.0]
        assert odom["stamp"] == [1_700_000_000, 250_000_000]
        assert odom["v"] == pytest.approx([2.0, 0.0], abs=1e-5)   # world +y seen from a body yawed 90 deg: forward
        imu = ros.of("msg", "/aero/imu")[0]
        assert imu["acc_z"] == pytest.approx(9.81) and imu["ocov0"] == -1.0   # no orientation estimate
        image = ros.of("msg", "/aero/camera/left/image_raw")[0]
        assert (image["h"], image["w"], image["enc"], image["step"], image["px"]) == (4, 6, "rgb8", 18, 200)
        cloud = ros.of("msg", "/aero/lidar/points")[0]
        assert cloud["n"] == 2 and cloud["fields"] == ["x", "y", "z", "intensity"] and cloud["point_step"] == 16
        assert cloud["first"] == pytest.approx([1.0, 2.0, 3.0, 0.5])
        det = ros.of("msg", "/aero/detections")[0]
        assert (det["n"], det["cls"], det["cx"], det["sx"]) == (1, "person", 320.0, 40.0)

        # ROS -> us: its PoseStamped becomes a goto goal at the mission.
        writes = [0]

        def goal_sent():
            ros.proc.stdin.write("goal\n")
            ros.proc.stdin.flush()
            writes[0] += 1
            return goals
        wait_until(goal_sent, 10, "the ROS goal at mission/action/goto/goal", interval_s=0.5)
        g = goals[0]
        assert (g.position_m.x, g.position_m.y, g.position_m.z) == (4.0, -3.0, 6.0)
        assert g.yaw_rad == pytest.approx(np.pi / 2, abs=1e-4)

        # Garbage on the goal topic: counted in the bridge's diagnostics, dropped, never a goal.
        goal_key = [d["key"] for d in ros.of("key", "/aero/goal")][0]
        # Each "goal" line is one ROS publish; bounded generously (a loaded CI host once took > 5 s)
        # and, if it never catches up, the node's state and stderr say why
        if not poll_until(lambda: len(ros.of("published")) == writes[0], 20, 0.05):
            raise AssertionError(f"the ROS node published {len(ros.of('published'))} of {writes[0]} goals asked; "
                                 f"alive {ros.proc.poll() is None}; stdout lines not reports: {list(ros.other)}; "
                                 f"its stderr: {ros.close()}")
        time.sleep(0.5)
        n_goals = len(goals)
        stack.session.put(goal_key, b"\x00\x01\x00\x00garbage")
        # /aero/vio/odom has no ROS subscriber: its samples are not even converted.
        vio = stack.publisher("state/visual_odometry", Odometry)
        for _ in range(3):
            vio.publish(Odometry())
        diag = wait_for_message(stack.session, "diagnostics/ros2bridge", DiagnosticStatus,
                                lambda d: int(d.values.get("invalid_msgs", 0)) >= 1
                                and int(d.values.get("skipped_no_subscriber", 0)) >= 3, timeout_s=5)
        assert "invalid=1" in str(diag.values.get("goals")), diag.values
        time.sleep(0.3)
        assert len(goals) == n_goals and bridge.poll() is None
    finally:
        err = ros.close()
        bridge.terminate()
        bridge.wait(8)
        log.close()
    assert "Traceback" not in err, err
