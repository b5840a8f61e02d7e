"""ros2bridge logic without Zenoh: rmw_zenoh names, hashes, attachment, conversions, goal checks."""
import math

import numpy as np
import pytest

from aeroperception.schemas import (
    Detection2D, Detection2DArray, Image, Imu, NDArray, PointCloud, Quaternion, Vector3, VehicleState,
)
from aeroperception.services.ros2bridge import contract
from aeroperception.services.ros2bridge.convert import CATALOG, GOAL_TYPE, Converter
from aeroperception.services.ros2bridge.rmw import RosNode, attachment, data_key, make_typestore, parse_attachment

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
