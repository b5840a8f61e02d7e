"""Contract of ros2bridge: which of our keys it reads, the mission action it calls, its parameters.

Its ROS side (rmw_zenoh keys `<domain>/<namespace>/<topic>/<type>/<hash>`, `@ros2_lv/**` tokens) is
not part of the stack's key space: see convert.CATALOG for the topic each key becomes.
"""
from aeroperception.schemas import (
    Detection2DArray, Image, Imu, Odometry, PointCloud, VehicleState,
)
from aeroperception.services.runtime import Param, Topic, Topics
from aeroperception.services.runtime.params import start_only_but

NAME = "ros2bridge"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState, note="-> <ns>/odom nav_msgs/Odometry"),
    Topic("state/visual_odometry", Odometry, note="-> <ns>/vio/odom nav_msgs/Odometry"),
    Topic("sensors/imu", Imu, note="-> <ns>/imu sensor_msgs/Imu"),
    Topic("sensors/camera/left/image", Image, note="-> <ns>/camera/left/image_raw sensor_msgs/Image"),
    Topic("sensors/camera/right/image", Image, note="-> <ns>/camera/right/image_raw"),
    Topic("sensors/lidar/points", PointCloud, note="-> <ns>/lidar/points sensor_msgs/PointCloud2"),
    Topic("perception/obstacles", PointCloud, note="-> <ns>/perception/obstacles sensor_msgs/PointCloud2"),
    Topic("perception/detections", Detection2DArray, note="-> <ns>/detections vision_msgs/Detection2DArray"),
)
# <ns>/goal geometry_msgs/PoseStamped (ENU "map") -> a goto goal, checked by the mission as any other.
ACTION_CALLS = ("mission/action/goto",)
_DECLARED = [
    Param("domain_id", 0, "", 0, 232, description="ROS_DOMAIN_ID of the ROS 2 graph to join"),
    Param("namespace", "/aero", description="ROS namespace of the bridge node and its topics"),
    Param("node_name", "aero_bridge", description="ROS node name"),
    Param("topics", "state/vehicle,state/visual_odometry,sensors/imu,perception/detections",
          description="comma-separated keys to publish to ROS (any of INPUTS; images and clouds cost CPU)"),
    Param("max_rate_hz", 20.0, "Hz", 0.1, 200.0, description="per-topic cap: extra samples are dropped, never queued"),
    Param("goal_topic", "goal", description="PoseStamped goal topic under the namespace (empty: no ROS commands)"),
]
# The bridge declares its ROS entities from its parameters at start: a live set is refused, saying so.
PARAMS = start_only_but(_DECLARED)
