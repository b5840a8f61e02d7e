"""ros2bridge logic without Zenoh: rmw_zenoh names, hashes, attachment, conversions, goal checks."""
import math
import types

import numpy as np
import pytest

from aeroperception.schemas import (
    Detection2D, Detection2DArray, Image, Imu, NDArray, PointCloud, Quaternion, Vector3, VehicleState,
)
from aeroperception.services.ros2bridge import contract
from aeroperception.services.ros2bridge.bridge import RosBridgeConfig, TopicBridge, ros_name
from aeroperception.services.ros2bridge.convert import CATALOG, GOAL_TYPE, Converter
from aeroperception.services.ros2bridge.rmw import RosNode, attachment, data_key, make_typestore, parse_attachment
from aeroperception.services.runtime.config import build

STORE = make_typestore()
CONV = Converter(STORE)


def test_type_hashes_are_computed_and_match_the_ones_real_rmw_zenoh_keys_carry():
    # Seen on rmw_zenoh data keys in the wild (Jazzy): computed here from the type descriptions.
    assert STORE.hash_rihs01("nav_msgs/msg/Odometry") == \
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
    assert STORE.hash_rihs01(GOAL_TYPE).startswith("RIHS01_10f3786d7d40fd2b")


def test_keys_and_liveliness_tokens_follow_rmw_zenoh():
    h = STORE.hash_rihs01("sensor_msgs/msg/Imu")
    assert data_key(0, "/aero/imu", "sensor_msgs/msg/Imu", h) == f"0/aero/imu/sensor_msgs::msg::dds_::Imu_/{h}"
    node = RosNode(domain_id=3, zid="abc", namespace="/aero", name="aero_bridge")
    assert node.token() == "@ros2_lv/3/abc/0/0/NN/%/%aero/aero_bridge"
    assert node.endpoint_token("MP", 5, "/aero/imu", "sensor_msgs/msg/Imu", h) == \
        f"@ros2_lv/3/abc/0/5/MP/%/%aero/aero_bridge/%aero%imu/sensor_msgs::msg::dds_::Imu_/{h}/::,10:,:,:,,"


def test_attachment_is_33_bytes_and_round_trips():
    gid = bytes(range(16))
    a = attachment(7, 1_700_000_000_000_000_001, gid)
    assert len(a) == 33 and parse_attachment(a) == (7, 1_700_000_000_000_000_001, gid)
    with pytest.raises(ValueError):
        parse_attachment(a[:10])


def test_every_catalog_entry_is_an_input_of_the_contract_and_serializes():
    assert set(CATALOG) == set(contract.INPUTS)
    samples = {
        VehicleState: VehicleState(), Imu: Imu(),
        Image: Image(height=2, width=2, encoding="mono8", data=NDArray.from_numpy(np.zeros((2, 2), np.uint8))),
        PointCloud: PointCloud(points=NDArray.from_numpy(np.zeros((3, 3), np.float32))),
        Detection2DArray: Detection2DArray(detections=[Detection2D(class_id=2, score=0.5)]),
    }
    for key, b in CATALOG.items():
        cls = contract.INPUTS[key]
        msg = samples.get(cls) or cls()
        cdr = bytes(STORE.serialize_cdr(getattr(CONV, b.convert)(msg), b.ros_type))
        assert cdr[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation header
        STORE.deserialize_cdr(cdr, b.ros_type)


def test_vehicle_velocity_is_rotated_into_the_body_frame_for_ros_odometry():
    yaw90 = Quaternion(w=math.sqrt(0.5), x=0.0, y=0.0, z=math.sqrt(0.5))
    odom = CONV.from_vehicle_state(VehicleState(orientation=yaw90, velocity_mps=Vector3(x=1.0, y=0.0, z=0.5)))
    lin = odom.twist.twist.linear
    assert (lin.x, lin.y, lin.z) == pytest.approx((0.0, -1.0, 0.5), abs=1e-9)   # east = the body's right


def _pose_stamped(frame="map", x=1.0, qz=0.0, qw=1.0):
    T = STORE.types
    return T[GOAL_TYPE](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=frame),
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=2.0, z=5.0),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=qz, w=qw)))


def test_goal_from_ros_pose_stamped_and_what_it_refuses():
    g = CONV.goal_from_pose_stamped(_pose_stamped(qz=1.0, qw=0.0))
    assert (g.position_m.x, g.position_m.y, g.position_m.z) == (1.0, 2.0, 5.0) and g.yaw_rad == pytest.approx(math.pi)
    assert CONV.goal_from_pose_stamped(_pose_stamped(qz=0.0, qw=0.0)).yaw_rad is None   # no orientation: keep heading
    with pytest.raises(ValueError, match="frame"):
        CONV.goal_from_pose_stamped(_pose_stamped(frame="base_link"))
    with pytest.raises(ValueError, match="non-finite"):
        CONV.goal_from_pose_stamped(_pose_stamped(x=float("nan")))


class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _bridge(convert=CONV.from_imu, max_rate_hz=10.0):
    sent, reported, clock = [], [], _Clock()
    b = TopicBridge("sensors/imu", "sensor_msgs/msg/Imu", convert, STORE.serialize_cdr,
                    lambda cdr, attachment: sent.append((cdr, parse_attachment(attachment))), max_rate_hz,
                    lambda key, error: reported.append((key, error)), clock)
    return b, sent, reported, clock


def test_a_topic_nobody_on_the_ros_side_hears_is_not_converted():
    b, sent, _, _ = _bridge(convert=lambda msg: pytest.fail("converted for nobody"))
    b.on_message(Imu())
    assert (b.unheard, b.sent, sent) == (1, 0, [])


def test_samples_faster_than_max_rate_are_dropped_never_queued():
    b, sent, _, clock = _bridge(max_rate_hz=10.0)
    b.on_matching(types.SimpleNamespace(matching=True))
    for _ in range(5):                      # 5 samples within 40 ms: one goes out
        b.on_message(Imu())
        clock.t += 0.01
    clock.t += 0.1
    b.on_message(Imu())
    assert (b.sent, b.dropped) == (2, 4)
    assert [seq for _, (seq, _, gid) in sent] == [1, 2] and all(gid == b.gid for _, (_, _, gid) in sent)
    assert STORE.deserialize_cdr(sent[0][0], "sensor_msgs/msg/Imu")


def test_an_unconvertible_sample_is_counted_and_reported_not_raised():
    def broken(msg):
        raise ValueError("no such field")

    b, sent, reported, _ = _bridge(convert=broken)
    b.on_matching(types.SimpleNamespace(matching=True))
    b.on_message(Imu())
    assert (b.errors, b.sent, sent) == (1, 0, [])
    assert reported == [("sensors/imu", "cannot convert to sensor_msgs/msg/Imu: no such field")]


def test_topics_parameter_names_only_catalog_keys():
    cfg = build(RosBridgeConfig, contract.PARAMS)
    assert cfg.bridged_keys() == ["state/vehicle", "state/visual_odometry", "sensors/imu", "perception/detections"]
    with pytest.raises(ValueError, match="topics: sensors/radar cannot be bridged; choose from state/vehicle"):
        build(RosBridgeConfig, contract.PARAMS, topics="sensors/imu, sensors/radar").bridged_keys()
    assert ros_name("/aero/", "/vio/odom") == "/aero/vio/odom" and ros_name("", "imu") == "/imu"
