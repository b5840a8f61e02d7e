"""Contract of ros2bridge: which of our keys it reads (to ROS), which it publishes (from a vendor's
ROS 2 sensor drivers), the mission action it calls, its parameters.

Its ROS side (rmw_zenoh keys `<domain>/<namespace>/<topic>/<type>/<hash>`, `@ros2_lv/**` tokens) is
not part of the stack's key space: see convert.CATALOG for the topic each key becomes, and the
`inputs` parameter for the topics that feed OUTPUTS (only the keys it names are published).
Frames as the stack's: images in the camera's optical frame, the IMU in the body FLU frame
(REP-103), clouds in the sensor frame; a camera's place on the body from its `<side>_mount_*`.
"""
from aeroperception.schemas import (
    CameraInfo, Detection2DArray, Image, Imu, Odometry, PointCloud, VehicleState,
)
from aeroperception.services.runtime import BULK, SMALL, Param, Topic, Topics
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
# A vendor's ROS 2 drivers -> the stack, each key fed by the topic `inputs` names (QoS as the simulator's).
OUTPUTS = Topics(
    Topic("sensors/camera/left/image", Image, note="<- sensor_msgs/Image (mono8/16, rgb8, bgr8) or CompressedImage",
          qos=BULK),
    Topic("sensors/camera/right/image", Image, note="<- Image, or CompressedImage on a topic ending /compressed",
          qos=BULK),
    Topic("sensors/camera/left/info", CameraInfo, note="<- sensor_msgs/CameraInfo (plumb_bob) + left_mount_*"),
    Topic("sensors/camera/right/info", CameraInfo, note="<- sensor_msgs/CameraInfo + right_mount_*"),
    Topic("sensors/imu", Imu, note="<- sensor_msgs/Imu (FLU body frame)", qos=SMALL),
    Topic("sensors/lidar/points", PointCloud, note="<- sensor_msgs/PointCloud2 with float32 x, y, z", qos=BULK),
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
    Param("inputs", "", description="ROS topics feeding our sensors/**: ros_topic=our_key,... (a relative topic is "
                                    "under the namespace; an image topic ending /compressed is a CompressedImage)"),
    Param("left_mount_x_m", 0.0, "m", -5.0, 5.0, description="left camera position in the body (FLU), for its CameraInfo"),
    Param("left_mount_y_m", 0.0, "m", -5.0, 5.0), Param("left_mount_z_m", 0.0, "m", -5.0, 5.0),
    Param("left_mount_roll_deg", 0.0, "deg", -180.0, 180.0,
          description="left camera attitude in the body, its x along the optical axis (0, 0, 0: forward)"),
    Param("left_mount_pitch_deg", 0.0, "deg", -90.0, 90.0, description="+90: looking straight down"),
    Param("left_mount_yaw_deg", 0.0, "deg", -180.0, 180.0),
    Param("right_mount_x_m", 0.0, "m", -5.0, 5.0, description="right camera position in the body (FLU), for its CameraInfo"),
    Param("right_mount_y_m", 0.0, "m", -5.0, 5.0), Param("right_mount_z_m", 0.0, "m", -5.0, 5.0),
    Param("right_mount_roll_deg", 0.0, "deg", -180.0, 180.0,
          description="right camera attitude in the body, its x along the optical axis (0, 0, 0: forward)"),
    Param("right_mount_pitch_deg", 0.0, "deg", -90.0, 90.0, description="+90: looking straight down"),
    Param("right_mount_yaw_deg", 0.0, "deg", -180.0, 180.0),
]
# The bridge declares its ROS entities from its parameters at start: a live set is refused, saying so.
PARAMS = start_only_but(_DECLARED)
