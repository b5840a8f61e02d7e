"""Contract of the camera driver: keys out, the camera models it serves, and its parameters.

Frames: images in each camera's optical frame (camera_left_optical, camera_right_optical: x right,
y down, z forward); where the cameras sit on the body (T_body_camera in each info) comes from the
calibration file when it says (Kalibr's T_cam_imu), else from the mount_* parameters for the left
camera and the stereo calibration for the right one. Never assumed.
"""
from aeroperception.schemas import CameraInfo, Image
from aeroperception.services.runtime import BULK, Param, Queries, Query, Topic, Topics
from aeroperception.services.runtime.params import start_only_but

from .calibration import FORMATS

NAME = "camera"
CPU_BUDGET_PCT = 20.0    # % of one core: a 752x480 stereo pair at 20 Hz, decode and publish
OUTPUTS = Topics(
    Topic("sensors/camera/left/image", Image, 20.0, note="stamped at exposure (capture time - latency_s)", qos=BULK),
    Topic("sensors/camera/right/image", Image, 20.0, note="stereo layouts: same stamp as its left image", qos=BULK),
    Topic("sensors/camera/left/info", CameraInfo, 1.0, note="with a calibration; also served"),
    Topic("sensors/camera/right/info", CameraInfo, 1.0),
)
SERVICES = Queries(
    Query("sensors/camera/left/info", None, CameraInfo, note="the camera model, for a late subscriber"),
    Query("sensors/camera/right/info", None, CameraInfo),
)
_DECLARED = [
    Param("source", "/dev/video0", start_only=True,
          description="a V4L2 device (/dev/videoN or its index), gst:<GStreamer pipeline ending in appsink>, "
                      "a video file or a folder of images"),
    Param("source_right", "", start_only=True, description="layout stereo: the right camera's source"),
    Param("layout", "mono", choices=("mono", "stereo", "side_by_side"), start_only=True,
          description="mono; stereo = two sources grabbed together; side_by_side = one frame, left | right"),
    Param("calibration_path", "", start_only=True,
          description="OpenCV, Kalibr camchain or ROS camera_info YAML ('' = uncalibrated: images only, WARN)"),
    Param("calibration_path_right", "", start_only=True, description="ROS format: the right camera's file"),
    Param("calibration_format", "auto", choices=FORMATS, start_only=True),
    Param("rate_hz", 20.0, "Hz", 1.0, 120.0,
          description="devices: the frame rate asked for; files and folders: the pace they are played at"),
    Param("width", 0, "px", 0, 8192, start_only=True, description="devices: the width asked for (0 = its default)"),
    Param("height", 0, "px", 0, 8192, start_only=True, description="devices: the height asked for (0 = its default)"),
    Param("encoding", "mono8", choices=("mono8", "mono16", "rgb8", "bgr8"), description="published pixel encoding"),
    Param("latency_s", 0.0, "s", 0.0, 1.0,
          description="exposure to capture: the stamp is the capture time minus this (measure it: docs)"),
    Param("stall_timeout_s", 1.0, "s", 0.1, 30.0, description="no frame for this long: stalled, the device re-opened"),
    Param("reopen_period_s", 2.0, "s", 0.1, 60.0, description="between attempts to open a source that failed"),
    Param("loop", False, description="files and folders: start again at the end"),
    Param("mount_x_m", 0.0, "m", -5.0, 5.0, description="left camera position in the body (FLU)"),
    Param("mount_y_m", 0.0, "m", -5.0, 5.0),
    Param("mount_z_m", 0.0, "m", -5.0, 5.0),
    Param("mount_roll_deg", 0.0, "deg", -180.0, 180.0,
          description="left camera attitude in the body, its x along the optical axis (0, 0, 0: looking forward)"),
    Param("mount_pitch_deg", 0.0, "deg", -90.0, 90.0, description="+90: looking straight down"),
    Param("mount_yaw_deg", 0.0, "deg", -180.0, 180.0),
]
# The source, its layout, calibration and mount are taken at start (the camera models are built
# once); what the capture loop reads on every frame can change live.
PARAMS = start_only_but(_DECLARED, live=("encoding", "latency_s", "stall_timeout_s", "reopen_period_s", "loop"))
MOUNT_PARAMS = [p.name for p in PARAMS if p.name.startswith("mount_")]
