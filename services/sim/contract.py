"""Contract of the simulator: the keys it publishes (sensors, ground truth, clock), the camera
models it serves, and its parameters (the vehicle's and the shell's).

The vehicle itself talks MAVLink to fmu (services/sim/vehicle), not Zenoh; camera and LiDAR keys
are published by the render processes (render.py), the rest by the shell (main.py).
"""
from aeroperception.schemas import CameraInfo, Clock, Detection2DArray, Image, Imu, PointCloud, VehicleState
from aeroperception.services.runtime import BULK, SMALL, Param, Queries, Query, Topic, Topics

from .vehicle import PARAMS as VEHICLE_PARAMS

NAME = "sim"
# --follow only: an external FC's ground truth to render from, and its IMU to measure the stamps against
INPUTS = Topics(
    Topic("fmu/out/vehicle_ground_truth", VehicleState, note="--follow: the FC's ground truth (fmu)"),
    Topic("fmu/out/sensor_combined", Imu, note="--follow: the FC's IMU (fmu; also its sensors/imu), for truth_imu_lag_ms"),
)
# The sensor streams are declared here once: the cameras rendered (render.py), their infos published
# and served (main.py), the thin-link rules (qos=BULK: tools/cli/router.py) all follow these lines.
# QoS (services/sim/qos.py says why): SMALL streams ahead of the frames, BULK frames and scans behind.
OUTPUTS = Topics(
    Topic("sim/clock", Clock, 100.0, note="sim time (truth_rate_hz)", qos=SMALL),
    Topic("sim/truth/state", VehicleState, 100.0, note="pose, velocity, acceleration (ENU; truth_rate_hz)", qos=SMALL),
    Topic("sim/truth/boxes", Detection2DArray, note="with each left image: projected targets"),
    Topic("sim/truth/lidar_labels", PointCloud, note="with each scan: per-point labels", qos=BULK),
    Topic("sensors/imu", Imu, 200.0, note="FLU (the scenario's IMU rate)", qos=SMALL),
    Topic("sensors/camera/left/image", Image, 20.0, note="the scenario's camera rate, as the renderer achieves", qos=BULK),
    Topic("sensors/camera/right/image", Image, 20.0, note="same stamp as its left image", qos=BULK),
    Topic("sensors/camera/down/image", Image, 20.0, qos=BULK,
          note="the scenario's sensors.down_camera, if enabled: at most its rate_hz, rendered only while subscribed"),
    Topic("sensors/camera/left/info", CameraInfo, 1.0, note="also served (latched)"),
    Topic("sensors/camera/right/info", CameraInfo, 1.0),
    Topic("sensors/camera/down/info", CameraInfo, 1.0),
    Topic("sensors/lidar/points", PointCloud, 10.0, note="sensor frame", qos=BULK),
)
# --follow: no sim/clock (the FC's clock is real time) and no IMU of its own (the FC's is sensors/imu)
FOLLOW_OUTPUTS = Topics(*(t for k, t in OUTPUTS.declared.items() if k not in ("sim/clock", "sensors/imu")))
SERVICES = Queries(
    Query("sensors/camera/left/info", None, CameraInfo, note="the camera model, for a late subscriber"),
    Query("sensors/camera/right/info", None, CameraInfo),
    Query("sensors/camera/down/info", None, CameraInfo),
)
# Derived from OUTPUTS, never listed again: the cameras (sensors/camera/<name>/image), the keys each
# render process publishes, and what `--sensors` may choose (sim, aero up, aero bench).
CAMERAS = tuple(k.split("/")[2] for k in OUTPUTS if k.startswith("sensors/camera/") and k.endswith("/image"))
RENDERED = {"lidar": ("sensors/lidar/points", "sim/truth/lidar_labels"),
            "camera": (*(f"sensors/camera/{c}/image" for c in CAMERAS), "sim/truth/boxes")}
# --sensors: which renderers run (the IMU is the shell's): all, one of RENDERED (+ the IMU), imu, none
SENSOR_CHOICES = ("all", *RENDERED, "imu", "none")
SHELL_PARAMS = [
    Param("truth_rate_hz", 100.0, "Hz", 1.0, 250.0, description="sim/truth/state and sim/clock rate"),
]
PARAMS = [*VEHICLE_PARAMS, *SHELL_PARAMS]
