"""rmw_zenoh's wire format, so ROS 2 nodes on rmw_zenoh see our data with no bridge process of
theirs.

- data key     `<domain>/<topic without leading '/'>/<pkg>::msg::dds_::<Type>_/<RIHS01 hash>`
- payload      CDR with its 4-byte encapsulation header (rosbags: Apache-2.0, pure Python)
- attachment   sequence number (i64), source timestamp ns (i64), GID length (u8 = 16), GID
- liveliness   `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>`
               `[/<topic>/<dds type>/<hash>/<qos>]`, names with '/' mangled to '%'
Type hashes are computed from the type descriptions (REP-2011 RIHS01, rosbags' `hash_rihs01`),
never written down: a changed definition changes the key, as it does in ROS.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

ADMIN_SPACE = "@ros2_lv"
# Reliable, volatile, keep-last 10 (rmw_zenoh's compact QoS string; empty fields = defaults).
QOS_DEFAULT = "::,10:,:,:,,"
# Best effort, volatile, keep-last 10: a subscription any publisher matches, reliable or
# best effort (drivers publish with SensorDataQoS: best effort).
QOS_SENSOR_DATA = "2::,10:,:,:,,"

# vision_msgs (ROS 2 Humble/Jazzy, vision_msgs 4.x) is not in rosbags' ROS 2 store: its
# definitions, field for field as the package ships them (comments dropped).
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose":
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D":
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox2D bbox\nstring id\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}


def make_typestore():
    """ROS 2 Jazzy's standard types plus vision_msgs, in a store of our own."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def dds_type_name(ros_type: str) -> str:
    """"nav_msgs/msg/Odometry" -> "nav_msgs::msg::dds_::Odometry_"."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return "%" if name in ("", "/") else name.replace("/", "%")


def data_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class RosNode:
    """Who we are in the ROS graph: one node per bridge process."""

    domain_id: int
    zid: str
    namespace: str
    name: str
    node_id: int = 0
    enclave: str = "%"

    def token(self) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{self.node_id}/NN/"
                f"{self.enclave}/{mangle(self.namespace)}/{mangle(self.name)}")

    def endpoint_token(self, kind: str, entity_id: int, topic: str, ros_type: str, type_hash: str,
                       qos: str = QOS_DEFAULT) -> str:
        """kind: "MP" (publisher) or "MS" (subscription)."""
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{self.enclave}/{mangle(self.namespace)}/{mangle(self.name)}/"
                f"{mangle(topic)}/{dds_type_name(ros_type)}/{type_hash}/{qos}")


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte rmw_zenoh publication attachment."""
    if len(gid) != 16:
        raise ValueError("a GID is 16 bytes")
    return struct.pack("<qqB", sequence, stamp_ns, len(gid)) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence, timestamp ns, gid) of a publication attachment; ValueError if malformed."""
    if len(data) < 17:
        raise ValueError(f"attachment of {len(data)} bytes, expected 33")
    seq, stamp, n = struct.unpack_from("<qqB", data)
    if len(data) < 17 + n:
        raise ValueError("attachment GID truncated")
    return seq, stamp, bytes(data[17:17 + n])
