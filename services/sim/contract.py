"""Contract of the simulator: the keys it publishes (sensors, ground truth, clock), the camera
models it serves, and its parameters (the vehicle's and the shell's).

The vehicle itself talks MAVLink to fmu (services/sim/vehicle), not Zenoh; camera and LiDAR keys
are published by the render processes (render.py), the rest by the shell (main.py).
"""
from aeroperception.schemas import CameraInfo, Clock, Detection2DArray, Image, Imu, PointCloud, VehicleState
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics

from .vehicle import PARAMS as VEHICLE_PARAMS

NAME = "sim"
# --follow only: an external FC's ground truth to render from, and its IMU to measure the stamps against
INPUTS = Topics(
    Topic("fmu/out/vehicle_ground_truth", VehicleState, note="--follow: the FC's ground truth (fmu)"),
    Topic("fmu/out/sensor_combined", Imu, note="--follow: the FC's IMU (fmu; also its sensors/imu), for truth_imu_lag_ms"),
)
OUTPUTS = Topics(
    Topic("sim/clock", Clock, 100.0, note="sim time (truth_rate_hz)"),
    Topic("sim/truth/state", VehicleState, 100.0, note="pose, velocity, acceleration (ENU; truth_rate_hz)"),
    Topic("sim/truth/boxes", Detection2DArray, note="with each left image: projected targets"),
    Topic("sim/truth/lidar_labels", PointCloud, note="with each scan: per-point labels"),
    Topic("sensors/imu", Imu, 200.0, note="FLU (the scenario's IMU rate)"),
    Topic("sensors/camera/left/image", Image, 20.0, note="the scenario's camera rate, as the renderer achieves"),
    Topic("sensors/camera/right/image", Image, 20.0, note="same stamp as its left image"),
    Topic("sensors/camera/left/info", CameraInfo, 1.0, note="also served (latched)"),
    Topic("sensors/camera/right/info", CameraInfo, 1.0),
    Topic("sensors/lidar/points", PointCloud, 10.0, note="sensor frame"),
)
# --follow: no sim/clock (the FC's clock is real time) and no IMU of its own (the FC's is sensors/imu)
FOLLOW_OUTPUTS = Topics(*(t for k, t in OUTPUTS.declared.items() if k not in ("sim/clock", "sensors/imu")))
SERVICES = Queries(
    Query("sensors/camera/left/info", None, CameraInfo, note="the camera model, for a late subscriber"),
    Query("sensors/camera/right/info", None, CameraInfo),
)
SHELL_PARAMS = [
    Param("truth_rate_hz", 100.0, "Hz", 1.0, 250.0, description="sim/truth/state and sim/clock rate"),
]
PARAMS = [*VEHICLE_PARAMS, *SHELL_PARAMS]
